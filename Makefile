# Two commands: `make demo` and `make test`. Both create .venv when it is missing.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint bench clean

TEST_WORKERS ?= 2
# test processes; the suite is sized for 2 cores (`make test TEST_WORKERS=auto` on more)

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	MPLBACKEND=Agg $(BIN)/haptic run --plot demo.png --json demo.json

test: $(STAMP)
	$(BIN)/ruff check firmware_if sim_backend service tools tests
	MPLBACKEND=Agg $(BIN)/python -m pytest -n $(TEST_WORKERS)

lint: $(STAMP)
	$(BIN)/ruff check firmware_if sim_backend service tools tests

bench: $(STAMP)
	MPLBACKEND=Agg $(BIN)/haptic bench paper --json bench-paper.json --plot bench-paper.png

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache .ruff_cache
