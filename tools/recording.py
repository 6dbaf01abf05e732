"""Recordings of hapticd's stream, in MCAP, the log container Foxglove and ROS 2 tools read.

One MCAP channel per stream topic (`state`, `estimate`, `cloud`, `event`), each with a JSON
Schema (schema encoding `jsonschema`) and JSON messages (message encoding `json`): every
wire message as its msgpack map says it (docs/protocol.md), envelope included, arrays as
nested lists whose schema carries `x-dtype` so they can be turned back into arrays. A
message's log time is when the recorder received it (ns since the epoch), its publish
time the daemon's `t_wall_ns`, its sequence the topic's `seq`. The daemon's config (its
`get_config` result) is a metadata record `hapticd` with one key, `config` (JSON).

Older `.hrec` files (msgpack: a header, then {topic, t_ns, payload}) are read alike.
"""

from __future__ import annotations

import json
import math
import struct
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import msgpack

from service.errors import InputError
from service.wire import envelope as wire

MCAP_MAGIC = b"\x89MCAP0\r\n"
HREC_FORMAT = "haptic-record"
LIBRARY = "haptic-slam record"
CHUNK_BYTES = 32 * 1024
"""Messages a chunk holds before it is compressed and written: a recorder killed outright
(SIGKILL, a crash) leaves every chunk before the last in the file, and `read_recording`
reads them. At MCAP's default of 1 MB such a file was empty."""

_NUM, _INT, _STR, _BOOL = ({"type": "number"}, {"type": "integer"}, {"type": "string"},
                           {"type": "boolean"})
_POSE = {"type": ["array", "null"], "items": _NUM, "minItems": 3, "maxItems": 3}
_ENVELOPE = {"v": _INT, "type": _STR, "seq": _INT, "t_mono_ns": _INT, "t_wall_ns": _INT}


def _schema(title: str, fields: dict[str, Any], *, open_: bool = False) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "type": "object", "properties": {**_ENVELOPE, **fields},
            "required": [*_ENVELOPE, *fields] if not open_ else [*_ENVELOPE, "event"],
            "additionalProperties": open_}


SCHEMAS: dict[str, dict[str, Any]] = {
    "state": _schema("haptic.state", {
        "state": _STR, "fault": {"type": ["string", "null"]},
        "fingers": {"type": "array", "items": {"type": "object", "properties": {
            "centre": {**_POSE, "type": "array"}, "joints": {"type": "array", "items": _NUM},
            "moving": _BOOL, "blocked": _BOOL}}},
        "moving": _BOOL, "dropped": _BOOL, "steps_done": _INT, "torque_on": _BOOL,
        "exploring": _BOOL, "phase": _STR,
        "episode": _INT, "lease_holder": {"type": ["string", "null"]},
        "timing": {"type": "object", "additionalProperties": {"type": ["number", "null"]}}}),
    "estimate": _schema("haptic.estimate", {
        "episode": _INT, "step": _INT, "pose": _POSE, "candidates": _INT,
        "converged": _BOOL, "position_sd": {"type": ["number", "null"]},
        "heading_sd": {"type": ["number", "null"]}, "mode_mass": {"type": ["number", "null"]},
        "runner_up": _POSE, "runner_up_mass": {"type": ["number", "null"]},
        "kind": _STR, "displacement": _POSE,
        "predicted_quality": {"type": ["number", "null"]},
        "quality": {"type": ["number", "null"]}}),
    "cloud": _schema("haptic.cloud", {
        "episode": _INT, "step": _INT, "total": _INT,
        "poses": {"type": "array", "x-dtype": "<f4", "description": "(N, 3): x0, y0 (m), "
                  "heading (rad)", "items": {"type": "array", "items": _NUM}},
        "weights": {"type": "array", "x-dtype": "<f4", "items": _NUM}}),
    "event": _schema("haptic.event", {"event": _STR}, open_=True),
}
"""A JSON Schema per topic (docs/protocol.md gives each field's meaning and unit)."""


@dataclass(frozen=True)
class Record:
    """One recorded stream message: its topic, when it was received (ns), the message."""

    topic: str
    t_ns: int
    message: wire.Message


# -- writing ---------------------------------------------------------------------------------
def _plain(value: Any) -> Any:
    """A decoded wire value as JSON: arrays as nested lists, non-finite floats as null.

    float32 elements are written with the fewest digits that read back to the same float32
    ('0.1', not '0.10000000149011612'): half the bytes of a cloud."""
    if getattr(value, "dtype", None) is not None and value.dtype.kind == "f" \
            and value.dtype.itemsize == 4:
        value = value.astype("U16").astype("f8")
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def message_json(msg: wire.Message) -> dict[str, Any]:
    """A message as the JSON object its MCAP channel carries (envelope + fields)."""
    return {"v": wire.VERSION, "type": msg.type, "seq": msg.seq, "t_mono_ns": msg.t_mono_ns,
            "t_wall_ns": msg.t_wall_ns, **_plain(msg.body)}


class McapRecorder:
    """Writes stream messages to an MCAP file; `close` (or leaving `with`) finishes it."""

    def __init__(self, path: str | Path) -> None:
        from mcap.writer import CompressionType, Writer

        try:
            self._file: IO[bytes] = open(path, "wb")  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise InputError(f"cannot write the recording '{path}': {exc.strerror}; give a "
                             "path in a folder that exists and you may write to") from None
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES,
                              compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=LIBRARY)
        self._channels = {}
        for topic, schema in SCHEMAS.items():
            sid = self._writer.register_schema(name=schema["title"], encoding="jsonschema",
                                               data=json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="json", schema_id=sid)
        self.count = 0

    def add_config(self, config: dict[str, Any]) -> None:
        """Store the daemon's config (`get_config`'s result) with the stream."""
        self._writer.add_metadata("hapticd", {"config": json.dumps(config)})
        self._file.flush()

    def write(self, topic: str, msg: wire.Message, received_ns: int | None = None) -> None:
        data = json.dumps(message_json(msg), allow_nan=False, separators=(",", ":")).encode()
        self._writer.add_message(self._channels[topic],
                                 log_time=received_ns or time.time_ns(), data=data,
                                 publish_time=msg.t_wall_ns, sequence=msg.seq)
        self._file.flush()  # a finished chunk reaches the file now, not at close
        self.count += 1

    def close(self) -> None:
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- reading ---------------------------------------------------------------------------------
def read_recording(path: str | Path) -> tuple[dict[str, Any] | None, list[Record]]:
    """The daemon config (if recorded) and the messages of an MCAP or `.hrec` recording."""
    try:
        with open(path, "rb") as f:
            magic = f.read(len(MCAP_MAGIC))
    except FileNotFoundError:
        raise InputError(f"recording '{path}' does not exist") from None
    except OSError as exc:
        raise InputError(f"cannot read '{path}': {exc.strerror}") from None
    if magic == MCAP_MAGIC:
        return _read_mcap(path)
    return _read_hrec(path)


def _read_mcap(path: str | Path) -> tuple[dict[str, Any] | None, list[Record]]:
    """Every record in file order, so a recording whose recorder was killed (no summary,
    the last chunk cut) gives what it holds, with a note on standard error."""
    from mcap.exceptions import EndOfFile, McapError
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    config, records = None, []
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    try:
        with open(path, "rb") as f:
            try:
                for record in StreamReader(f).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Metadata):
                        if record.name == "hapticd" and "config" in record.metadata:
                            config = json.loads(record.metadata["config"])
                    elif isinstance(record, Message) and record.channel_id in channels:
                        channel = channels[record.channel_id]
                        if channel.topic not in SCHEMAS:
                            continue
                        schema = schemas.get(channel.schema_id)
                        spec = (json.loads(schema.data) if schema is not None
                                else SCHEMAS[channel.topic])
                        records.append(Record(channel.topic, record.log_time,
                                              _haptic_message(path, channel, record.data, spec)))
            except (McapError, EOFError, struct.error) as exc:
                if not schemas and not channels and isinstance(exc, (EndOfFile, EOFError)):
                    raise InputError(f"'{path}' ends before its first record (it is empty "
                                     "or was cut at the start): there is nothing in it to "
                                     "read") from None
                if not schemas:
                    raise
                print(f"note: '{path}' ends early, as a recorder stopped without finishing it "
                      f"leaves it ({type(exc).__name__}); read the {len(records)} messages "
                      "before that", file=sys.stderr)
    except InputError:
        raise
    except (McapError, ValueError, KeyError, TypeError, EOFError, struct.error) as exc:
        raise InputError(f"'{path}' is not a readable MCAP recording: "
                         f"{type(exc).__name__}: {exc}"[:300]) from None
    if not any(channel.topic in SCHEMAS for channel in channels.values()):
        topics = sorted({channel.topic for channel in channels.values()})
        raise InputError(f"'{path}' holds no haptic-slam stream ("
                         + (f"its topics: {', '.join(topics)}"[:200] if topics else "no topics")
                         + "): it was not made by `haptic record`")
    records.sort(key=lambda r: r.t_ns)  # log time, as a player would
    return config, records


def _haptic_message(path: str | Path, channel: Any, data: bytes, spec: dict[str, Any]
                    ) -> wire.Message:
    """A message of a channel named like one of ours, or InputError saying it is not one of
    ours (another program's MCAP on the same topic names: a KeyError 'type', or a
    UnicodeDecodeError from a protobuf)."""
    try:
        if channel.message_encoding != "json":
            raise ValueError(f"encoded as {channel.message_encoding!r}, not JSON")
        obj = json.loads(data)
        if not isinstance(obj, dict):
            raise ValueError("not a JSON object")
        return message_from_json(obj, spec, channel.topic)
    except (ValueError, KeyError, TypeError) as exc:
        why = f"no field {exc}" if isinstance(exc, KeyError) else str(exc).splitlines()[0]
        raise InputError(f"'{path}' has a {channel.topic} channel whose messages are not "
                         f"haptic-slam's ({why[:120]}): it was not made by `haptic record`"
                         ) from None


def message_from_json(obj: dict[str, Any], schema: dict[str, Any], topic: str
                      ) -> wire.Message:
    """A JSON message back to a wire Message, lists with an `x-dtype` back to arrays."""
    import numpy as np

    body = {k: v for k, v in obj.items() if k not in _ENVELOPE}
    for name, spec in schema.get("properties", {}).items():
        if "x-dtype" in spec and name in body:
            body[name] = np.asarray(body[name], dtype=spec["x-dtype"])
    return wire.Message(type=obj["type"], seq=obj["seq"], t_mono_ns=obj["t_mono_ns"],
                        t_wall_ns=obj["t_wall_ns"], body=body, topic=topic)


def _read_hrec(path: str | Path) -> tuple[dict[str, Any] | None, list[Record]]:
    """Every record of an `.hrec` file; one damaged or cut part way (as MCAP, `_read_mcap`)
    gives what comes before the damage, with a note on standard error."""
    items: list[Any] = []
    damage = None
    with open(path, "rb") as f:
        unpacker = msgpack.Unpacker(f, raw=False, strict_map_key=True,
                                    max_buffer_size=64 * 1024 * 1024)
        try:
            for item in unpacker:
                items.append(item)
        except Exception as exc:  # msgpack's own errors, and ValueError for bad data
            damage = exc
    if not items or not isinstance(items[0], dict) or items[0].get("format") != HREC_FORMAT:
        raise InputError(f"'{path}' is not a haptic recording (neither MCAP nor .hrec)")
    if damage is not None or unpacker.tell() < Path(path).stat().st_size:
        why = "cut mid-record" if damage is None else type(damage).__name__
        print(f"note: '{path}' is damaged part way ({why}); read the {len(items) - 1} "
              "records before that", file=sys.stderr)
    records = []
    for r in items[1:]:
        if not (isinstance(r, dict) and isinstance(r.get("payload"), bytes)
                and isinstance(r.get("t_ns"), int) and r.get("topic") in SCHEMAS):
            continue
        try:
            records.append(Record(r["topic"], r["t_ns"],
                                  wire.decode(r["payload"], topic=r["topic"],
                                              versions=wire.READABLE_VERSIONS)))
        except wire.WireError:
            continue  # a damaged message is skipped, as a subscriber would
    return items[0].get("config"), records


def wire_payload(msg: wire.Message) -> bytes:
    """The message as the daemon sent it (msgpack, original envelope), to re-publish."""
    fields = {"v": wire.VERSION, "type": msg.type, "seq": msg.seq, "t_mono_ns": msg.t_mono_ns,
              "t_wall_ns": msg.t_wall_ns}
    fields.update({k: wire.pack_array(v) if hasattr(v, "dtype") else v
                   for k, v in msg.body.items()})
    return msgpack.packb(fields, use_bin_type=True)
