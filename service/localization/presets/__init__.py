"""Built-in surfaces by name: `NAME[:SIZE[:SEED]]` and `profile:KIND[:SIZE[:SEED]]`.

Every family but `peaks` and `eggcrate` is seeded, so each seed is a new surface of the
same kind (the benchmarks keep surfaces no localizer was tuned on). SIZE is the side in
map units of 10 mm (`plate:30` is 300 mm square); every preset is sampled at 1 mm, with
heights in metres.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from service.errors import MapError
from service.localization.presets.classic import bumps, eggcrate, peaks
from service.localization.presets.plates import pattern, plate
from service.localization.presets.profiles import cut, smooth_profile
from service.localization.presets.shells import shell
from service.localization.presets.terrain import terrain
from service.localization.surface import HeightMap

SIZES = (2.0, 400.0)
"""Allowed sizes in map units."""


@dataclass(frozen=True)
class Preset:
    build: Callable[[float, int], HeightMap]
    summary: str
    seeded: bool = True
    default_size: float = 20.0


PRESETS: dict[str, Preset] = {
    "peaks": Preset(lambda size, seed: peaks(size),
                    "MATLAB's peaks, the paper's benchmark (B1)", seeded=False),
    "bumps": Preset(bumps, "smooth random bumps about 15 mm wide, 20 mm high (B2, B3)"),
    "eggcrate": Preset(lambda size, seed: eggcrate(size),
                       "a periodic egg-crate: genuinely ambiguous, the answer is 'not yet'",
                       seeded=False),
    "plate": Preset(plate, "a machined plate on a table: large plains with pockets, holes "
                           "(some narrower than the tip), bosses, ribs, fillets"),
    "pattern": Preset(pattern, "a square plate with a symmetric pattern (four holes, a bolt "
                               "circle, a grid of pockets) broken by one feature: a chamfered "
                               "corner, a counterbore, a notch or a pin"),
    "shell": Preset(shell, "a curved panel (dome, saddle or cylinder) with small features: "
                           "rivet rows, a bead, dimples, a pad"),
    "terrain": Preset(terrain, "fractal terrain (spectral synthesis), roughness and relief "
                               "drawn by the seed, some with a flat basin"),
}

PROFILE = "profile"
PROFILE_SUMMARY = ("a 1-D profile: 'smooth' random bumps, or a row cut from any preset above "
                   "(the seed draws the surface and the row)")
FAMILIES = ("plate", "pattern", "shell", "terrain")
"""The surfaces like real objects (`haptic bench objects`)."""


def describe() -> list[tuple[str, str]]:
    """(syntax, summary) of every preset, for help texts and `haptic map list`."""
    rows = [(f"{name}[:SIZE{'[:SEED]' if p.seeded else ''}]", p.summary)
            for name, p in PRESETS.items()]
    return rows + [(f"{PROFILE}:KIND[:SIZE[:SEED]]", PROFILE_SUMMARY)]


def names() -> list[str]:
    return [*PRESETS, PROFILE]


def preset(spec: str) -> HeightMap:
    """The surface a spec names, e.g. `plate`, `plate:30:4`, `profile:terrain:20:2`."""
    return parse(spec)()


def parse(spec: str) -> Callable[[], HeightMap]:
    """What builds the surface a spec names, the spec checked (MapError) but nothing built
    yet: a configuration is checked whole before any surface is made."""
    name, *args = spec.split(":")
    if name == PROFILE:
        if not args:
            raise MapError(f"map preset '{spec}' needs a kind: profile:smooth, or profile:NAME "
                           f"with NAME one of {', '.join(PRESETS)}")
        kind, *args = args
        size, seed = _size_and_seed(spec, args, seeded=True)
        if kind == "smooth":
            return lambda: smooth_profile(size, seed)
        if kind not in PRESETS:
            raise MapError(f"map preset '{spec}': unknown profile kind '{kind}'; kinds are "
                           f"smooth, {', '.join(PRESETS)}")
        return lambda: cut(PRESETS[kind].build(size, seed), seed)
    entry = PRESETS.get(name)
    if entry is None:
        raise MapError(f"unknown map preset '{name}'; presets are {', '.join(names())} "
                       "(`haptic map list` describes them)")
    size, seed = _size_and_seed(spec, args, entry.seeded, entry.default_size)
    return lambda: entry.build(size, seed)


def _size_and_seed(spec: str, args: list[str], seeded: bool,
                   default_size: float = 20.0) -> tuple[float, int]:
    if len(args) > (2 if seeded else 1):
        raise MapError(f"map preset '{spec}' takes at most a size"
                       + (" and a seed" if seeded else ""))
    try:
        size = float(args[0]) if args else default_size
        seed = int(args[1]) if len(args) > 1 else 0
    except ValueError:
        raise MapError(f"map preset '{spec}': size and seed must be numbers, e.g. "
                       "bumps:40:3 (size in units of 10 mm, seed a whole number)") from None
    if not SIZES[0] <= size <= SIZES[1]:
        raise MapError(f"map preset '{spec}': size must be {SIZES[0]:g}..{SIZES[1]:g} units")
    if seed < 0:
        raise MapError(f"map preset '{spec}': the seed must be >= 0")
    return size, seed
