"""`haptic record` writes MCAP that the mcap library reads; `haptic export` gives back the
episode `haptic run --json` writes; `haptic replay` still reads old `.hrec` files."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
from pathlib import Path

import msgpack
import pytest
from mcap.reader import make_reader

from service.daemon.harness import loopback_config, running_node
from service.wire import envelope as wire
from tools.cli import main

ROOT = Path(__file__).resolve().parents[2]
TIMINGS = ("compute_ms", "policy_ms", "background_ms", "settle_ms")


def without_timings(episode: dict) -> dict:
    return {**episode, "steps": [{k: v for k, v in s.items() if k not in TIMINGS}
                                 for s in episode["steps"]]}


def run_flags(settings: dict) -> list[str]:
    """`haptic run` options giving these settings (noise-free, no start pose)."""
    return ["--map", settings["map"], "--radius", str(settings["radius"]), "--step",
            str(settings["step"]), "--algorithm", settings["algorithm"], "--policy",
            settings["policy"], "--max-steps", str(settings["max_steps"]), "--headings",
            str(settings["headings"]), "--seed", str(settings["seed"])]


def test_record_export_round_trip_equals_haptic_run(tmp_path: Path, capsys) -> None:
    rec, exported, ran = tmp_path / "run.mcap", tmp_path / "e.json", tmp_path / "r.json"
    config = loopback_config({"backend": {"step_duration_s": 0.0}, "scenario": {"seed": 4}})
    with running_node(config) as node:
        ep = ["--pub", node.endpoints["pub"], "--cmd", node.endpoints["cmd"]]
        recorder = subprocess.Popen([sys.executable, "-m", "tools.cli", "record", str(rec),
                                     *ep, "--state-hz", "5"], cwd=ROOT, text=True,
                                    stderr=subprocess.PIPE)
        try:
            assert recorder.stderr.readline().startswith("# recording")  # subscribed
            assert main(["explore", *ep, "--quiet"]) == 0
        except BaseException:
            recorder.kill()
            raise
    _, err = recorder.communicate(timeout=60)  # the daemon's shutdown event ends it
    assert recorder.returncode == 0 and "Traceback" not in err
    # the mcap library's own reader: one channel per topic, JSON with JSON schemas
    with rec.open("rb") as f:
        summary = make_reader(f).get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    assert set(channels) == {"state", "estimate", "cloud", "event"}
    assert all(c.message_encoding == "json" for c in channels.values())
    assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
    counts = summary.statistics.channel_message_counts
    assert all(counts.get(c.id, 0) > 0 for c in channels.values()), counts
    # the episode, exported, is the one `haptic run` runs with the same settings
    assert main(["export", str(rec), "--json", str(exported), "--episode", "1"]) == 0
    episode = json.loads(exported.read_text())
    assert main(["run", "--quiet", "--json", str(ran), *run_flags(episode["settings"])]) == 0
    assert without_timings(episode) == without_timings(json.loads(ran.read_text()))
    assert episode["success"] is True
    # CSV: a row per step
    out = tmp_path / "steps.csv"
    assert main(["export", str(rec), "--csv", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == len(episode["steps"]) and rows[0]["dz_m"]
    capsys.readouterr()
    assert main(["replay", str(rec)]) == 0
    assert "CONVERGED" in capsys.readouterr().out


FINGER_EPISODE_3 = [
    ("episode_started", {"episode": 3, "candidates": 20000, "settings": None, "truth": None}),
    ("step", {"episode": 3, "index": 1, "move": 0, "command": [0.01, 0.0],
              "measurement": [0.01, 0.0, 0.002], "blocked": False, "candidates": 900,
              "compute_ms": 1.0, "policy_ms": 1.0, "estimate": [0.1, 0.1, 0.0]})]


def write_hrec(path: Path, events: list[tuple[str, dict]]) -> None:
    """An old-format recording (`.hrec`) of these events (a name of another topic, e.g.
    `estimate`, is a message of that topic)."""
    with path.open("wb") as f:
        f.write(msgpack.packb({"format": "haptic-record", "v": 1, "config": None}))
        for seq, (name, fields) in enumerate(events, 1):
            topic = name if name in ("state", "estimate", "cloud") else "event"
            payload = wire.encode(topic, seq, fields if topic != "event"
                                  else {"event": name, **fields})
            f.write(msgpack.packb({"topic": topic, "t_ns": seq, "payload": payload}))


def test_replay_and_export_still_read_an_old_hrec(tmp_path: Path, capsys) -> None:
    old = tmp_path / "old.hrec"
    write_hrec(old, FINGER_EPISODE_3)
    assert main(["replay", str(old)]) == 0
    assert "episode_started" in capsys.readouterr().out
    assert main(["export", str(old), "--json", "-"]) == 0
    captured = capsys.readouterr()
    (episode,) = json.loads(captured.out)
    assert episode["initial_candidates"] == 20000 and len(episode["steps"]) == 1
    assert episode["converged"] is False and "still running" in captured.err


@pytest.mark.parametrize("damage", ["cut", "garbled"])
def test_a_damaged_hrec_gives_what_comes_before_the_damage(tmp_path: Path, capsys,
                                                           damage: str) -> None:
    """A damaged `.hrec` was refused whole as "neither MCAP nor .hrec"; a cut MCAP file is
    read to where it stops, and so is this."""
    rec = tmp_path / "old.hrec"
    write_hrec(rec, FINGER_EPISODE_3)
    tail = b"\xc1\xc1\xc1" if damage == "garbled" else b""  # 0xc1: never valid msgpack
    rec.write_bytes(rec.read_bytes()[:-5] + tail)  # the last record cut (then junk)
    assert main(["replay", str(rec)]) == 0
    captured = capsys.readouterr()
    assert "episode_started" in captured.out
    assert f"note: '{rec}' is damaged part way" in captured.err
    assert f"read the {len(FINGER_EPISODE_3) - 1} records before that" in captured.err


def test_export_writes_the_finger_episodes_of_a_recording_that_also_holds_a_hand(
        tmp_path: Path, capsys) -> None:
    """A daemon that ran a finger and then a hand: the whole export was refused for the
    hand's episode. The finger's are written, the hand's skipped with a note; asked for
    the hand's alone, it says why not."""
    rec = tmp_path / "both.hrec"
    write_hrec(rec, [*FINGER_EPISODE_3, ("episode_started", {
        "episode": 4, "candidates": 300, "settings": {"object": "keyed", "hand": "two-finger"},
        "truth": None})])
    assert main(["export", str(rec), "--json", "-"]) == 0
    captured = capsys.readouterr()
    (episode,) = json.loads(captured.out)
    assert episode["initial_candidates"] == 20000
    assert "skipped episode(s) 4: a hand's" in captured.err
    assert main(["export", str(rec), "--json", "-", "--episode", "4"]) == 2
    assert "episode 4 in" in capsys.readouterr().err


def test_an_exported_episode_says_how_it_ended(tmp_path: Path, capsys) -> None:
    """A held-out fault campaign: an episode a servo's fault cut short was exported like one
    that ran out of steps (nothing said why it ended). `ended` is the `episode_done`
    reason, and null for an episode the recording ended before it did."""
    rec = tmp_path / "cut.hrec"
    done = {"episode": 3, "steps": 1, "converged": False, "reason": "fault",
            "pose": [0.1, 0.1, 0.0], "candidates": 900}
    write_hrec(rec, [*FINGER_EPISODE_3, ("episode_done", done),
                     ("episode_started", {**FINGER_EPISODE_3[0][1], "episode": 5})])
    assert main(["export", str(rec), "--json", "-"]) == 0
    cut, unfinished = json.loads(capsys.readouterr().out)
    assert (cut["ended"], cut["converged"]) == ("fault", False)
    assert unfinished["ended"] is None


def test_view_draws_the_last_finger_episode_of_a_recording_that_ends_with_a_hand(
        tmp_path: Path, capsys) -> None:
    """Recorded without the daemon's config, a finger's episode on peaks then a hand's: the
    map was taken from the hand's settings, and `haptic view --from` said the daemon runs a
    hand. The finger's map is drawn and the hand's episode skipped, with a note."""
    rec = tmp_path / "both.hrec"
    finger = {"map": "peaks", "spacing": None}
    estimate = {"episode": 3, "step": 1, "kind": "finger", "pose": [0.1, 0.1, 0.0],
                "converged": False, "displacement": [0.01, 0.0, 0.0]}
    write_hrec(rec, [("episode_started", {**FINGER_EPISODE_3[0][1], "settings": finger}),
                     FINGER_EPISODE_3[1], ("estimate", estimate),
                     ("episode_started", {"episode": 4, "candidates": 300, "truth": None,
                                          "settings": {"object": "keyed"}}),
                     ("estimate", {**estimate, "episode": 4, "kind": "hand",
                                   "displacement": None})])
    png = tmp_path / "view.png"
    assert main(["view", "--from", str(rec), "--png", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert "skipped episode(s) 4: a hand's" in capsys.readouterr().err


def test_export_refuses_what_it_cannot_read(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 40)
    assert main(["export", str(bad), "--json", "-"]) == 2
    assert "not a readable MCAP recording" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "none.mcap"), "--csv", "-"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_a_recording_stopped_by_a_signal_is_a_complete_file(tmp_path: Path) -> None:
    rec = tmp_path / "cut.mcap"
    with running_node(loopback_config()) as node:
        recorder = subprocess.Popen([sys.executable, "-m", "tools.cli", "record", str(rec),
                                     "--pub", node.endpoints["pub"], "--cmd",
                                     node.endpoints["cmd"]], cwd=ROOT, text=True,
                                    stderr=subprocess.PIPE)
        assert recorder.stderr.readline().startswith("# recording")
        recorder.send_signal(signal.SIGTERM)
        _, err = recorder.communicate(timeout=30)
    assert recorder.returncode == 0 and "Traceback" not in err
    with rec.open("rb") as f:
        summary = make_reader(f).get_summary()  # written only by a finished file
    assert summary is not None and summary.statistics.message_count > 0


def test_a_cloud_survives_json_exactly_in_fewer_bytes() -> None:
    import numpy as np

    from tools.recording import SCHEMAS, message_from_json, message_json

    rng = np.random.default_rng(0)
    poses = rng.uniform(-4, 4, (500, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(500)).astype(np.float32)
    msg = wire.decode(wire.encode("cloud", 7, {"episode": 1, "step": 3, "total": 900,
                                               "poses": poses, "weights": weights}),
                      topic="cloud")
    text = json.dumps(message_json(msg))
    back = message_from_json(json.loads(text), SCHEMAS["cloud"], "cloud")
    assert back.body["poses"].dtype == np.float32 and np.array_equal(back["poses"], poses)
    assert np.array_equal(back["weights"], weights) and back.seq == 7
    as_doubles = json.dumps({"poses": poses.tolist(), "weights": weights.tolist()})
    assert len(text) < 0.7 * len(as_doubles)  # float32's shortest digits, not float64's


@pytest.mark.parametrize("host", ["127.0.0.1", "::1"])
def test_replay_republishes_the_messages_as_the_daemon_sent_them(tmp_path: Path,
                                                                  host: str) -> None:
    """On IPv6 loopback too: a held-out check's `--publish tcp://[::1]:P` passed the
    loopback check, then failed "No such device"."""
    import socket
    import threading

    import numpy as np

    from service.wire.client import Subscriber
    from tools.recording import McapRecorder

    poses = np.arange(9, dtype=np.float32).reshape(3, 3) / 7
    sent = [wire.decode(wire.encode("cloud", 5, {"episode": 2, "step": 1, "total": 9,
                                                 "poses": poses,
                                                 "weights": np.full(3, 1 / 3, np.float32)}),
                        topic="cloud"),
            wire.decode(wire.encode("event", 8, {"event": "episode_done", "episode": 2}),
                        topic="event")]
    rec = tmp_path / "r.mcap"
    with McapRecorder(rec) as recorder:
        for i, msg in enumerate(sent):
            recorder.write(msg.topic, msg, received_ns=1_000_000_000 + i * 100_000_000)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family) as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
    except OSError:
        pytest.skip(f"no {host} on this machine")
    endpoint = f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"
    with Subscriber(endpoint) as sub:  # connects as soon as the replay binds
        player = threading.Thread(target=main, args=(
            ["replay", str(rec), "--publish", endpoint, "--delay", "1"],))
        player.start()
        got = [sub.recv(10.0), sub.recv(10.0)]
        player.join(30)
    assert [(m.topic, m.seq, m.t_wall_ns) for m in got] == \
        [(m.topic, m.seq, m.t_wall_ns) for m in sent]
    assert np.array_equal(got[0]["poses"], poses) and got[0]["poses"].dtype == np.float32


def test_a_recorder_killed_outright_leaves_what_it_wrote(tmp_path: Path, capsys) -> None:
    """`kill -9` on `haptic record` left an empty file (MCAP's 1 MB chunks were still in
    memory), and replay called it not a recording. Chunks now reach the file as they fill,
    and a file with no summary is read up to where it stops."""
    import shutil

    from tools.recording import McapRecorder, read_recording

    rec, cut = tmp_path / "live.mcap", tmp_path / "cut.mcap"
    recorder = McapRecorder(rec)
    sent = 0

    def send() -> None:
        nonlocal sent
        recorder.write("event", wire.decode(wire.encode(
            "event", sent, {"event": "note", "text": f"message {sent}" * 20}), topic="event"))
        sent += 1

    while rec.stat().st_size < 4 * 32 * 1024:  # a few chunks on disk
        send()
    for _ in range(5):  # and a chunk under way, in memory
        send()
    shutil.copyfile(rec, cut)  # the file as a killed recorder leaves it
    _, records = read_recording(cut)
    assert 0 < len(records) < sent
    assert [r.message.seq for r in records] == list(range(len(records)))  # none skipped
    assert "ends early" in capsys.readouterr().err
    recorder.close()
    assert len(read_recording(rec)[1]) == sent  # a finished file holds every message


def _foreign_mcap(path: Path, topic: str, encoding: str, data: bytes) -> Path:
    from mcap.writer import Writer

    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="someone else's")
        channel = writer.register_channel(topic=topic, message_encoding=encoding,
                                          schema_id=0)
        writer.add_message(channel_id=channel, log_time=1, publish_time=1, data=data)
        writer.finish()
    return path


@pytest.mark.parametrize("topic, encoding, data, words", [
    ("/robot/pose", "json", b'{"x": 1}', "holds no haptic-slam stream (its topics: "
                                         "/robot/pose)"),
    ("state", "json", b'{"hello": 1}', "state channel whose messages are not haptic-slam's "
                                       "(no field 'type')"),
    ("event", "protobuf", b"\x08\x96\x01\xff\xfe", "encoded as 'protobuf', not JSON"),
])
def test_another_programs_mcap_is_told_apart(tmp_path: Path, capsys, topic, encoding, data,
                                             words) -> None:
    """A held-out check's MCAP files from another program: on other topics `replay`
    printed nothing and exited 0; on our topic names it answered "KeyError: 'type'" or a
    UnicodeDecodeError."""
    path = _foreign_mcap(tmp_path / "other.mcap", topic, encoding, data)
    for command in (["replay", str(path)], ["export", str(path), "--json", "-"]):
        assert main(command) == 2
        err = capsys.readouterr().err
        assert words in err and "not made by `haptic record`" in err, err
        assert err.count("\n") == 1


def test_a_recording_cut_before_its_first_record_says_so(tmp_path: Path, capsys) -> None:
    path = tmp_path / "magic.mcap"
    path.write_bytes(b"\x89MCAP0\r\n")
    assert main(["replay", str(path)]) == 2
    assert "ends before its first record" in capsys.readouterr().err  # was "EndOfFile: "


def test_recording_where_nothing_can_be_written_or_heard_says_so(tmp_path: Path,
                                                                 capsys) -> None:
    """`haptic record /nonexist/x.mcap` was a FileNotFoundError traceback; a recording
    made with no daemon said only "recorded 0 messages", and its replay nothing at all."""
    assert main(["record", str(tmp_path / "none" / "x.mcap"), "--duration", "0.1"]) == 2
    assert "cannot write the recording" in capsys.readouterr().err
    silent = tmp_path / "silent.mcap"
    assert main(["record", str(silent), "--duration", "0.3", "--pub",
                 f"ipc://{tmp_path}/nobody", "--cmd", f"ipc://{tmp_path}/nobody-cmd"]) == 0
    assert "nothing arrived: is hapticd running at ipc://" in capsys.readouterr().err
    assert main(["replay", str(silent)]) == 0
    assert "holds no messages" in capsys.readouterr().err
