"""The wire format: msgpack messages in one envelope, arrays as typed binary, never pickle.

Every message is a msgpack map ``{v, type, seq, t_mono_ns, t_wall_ns, ...fields}``.
A numpy array travels as a map ``{dtype, shape, data}`` (little-endian dtype string,
list of ints, raw bytes), which any language can read. Decoding is strict: a size limit
is checked before unpacking, msgpack's own container limits bound memory, extension types
are refused, and only whitelisted dtypes become arrays. docs/protocol.md is the spec.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import msgpack

if TYPE_CHECKING:
    import numpy as np

from service.errors import InputError

VERSION = 2
"""Schema version carried in every envelope as `v`. Version 2 made the finger a hand of
one: `state` carries `fingers`, `estimate` its `kind` and a hand's grasp quality."""
READABLE_VERSIONS = (1, 2)
"""Versions a recording may hold: `haptic replay` and `export` read older files too."""

MAX_MESSAGE_BYTES = 64 * 1024
"""Default size limit of one decoded message (commands are small)."""
MAX_FRAME_BYTES = 16 * 1024 * 1024
"""The largest frame any socket accepts (a stream message, a reply, a request's cap)."""

DTYPES = frozenset({"<f8", "<f4", "<i8", "<i4", "<i2", "<u8", "<u4", "<u2", "|u1", "|i1",
                    "|b1"})
"""Array dtypes accepted on the wire: little-endian numbers and bools, nothing with objects."""

MAX_ARRAY_DIMS = 4


class WireError(InputError):
    """A message could not be decoded or does not follow the envelope; `code` says which.
    `request_id` is the message's `id` as decoded, when it could still be read (a map whose
    keys are wrong decodes in full, so its reply can name the request)."""

    def __init__(self, code: str, message: str, request_id: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.request_id = request_id


@dataclass(frozen=True)
class Message:
    """A decoded message: the envelope plus its remaining fields (arrays as numpy)."""

    type: str
    seq: int
    t_mono_ns: int
    t_wall_ns: int
    body: dict[str, Any] = field(default_factory=dict)
    topic: str = ""

    def __getitem__(self, key: str) -> Any:
        return self.body[key]

    def get(self, key: str, default: Any = None) -> Any:
        return self.body.get(key, default)


def pack_array(a: np.ndarray) -> dict[str, Any]:
    """An array as `{dtype, shape, data}`, converted to little-endian and C order."""
    import numpy as np  # only arrays need it: clients without arrays start faster

    a = np.asarray(a)
    dtype = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    dt = dtype.str
    if dt not in DTYPES:
        raise WireError("bad_array", f"dtype {a.dtype} cannot go on the wire; use numbers")
    data = np.ascontiguousarray(a, dtype=dtype).tobytes()
    return {"dtype": dt, "shape": list(a.shape), "data": data}


def unpack_array(obj: dict[str, Any]) -> np.ndarray:
    """The inverse of `pack_array`, checking dtype, shape and byte count."""
    import numpy as np

    dt, shape, data = obj.get("dtype"), obj.get("shape"), obj.get("data")
    if dt not in DTYPES:
        raise WireError("bad_array", f"array dtype {dt!r} is not allowed")
    if (not isinstance(shape, list) or len(shape) > MAX_ARRAY_DIMS
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
                       for n in shape)):
        raise WireError("bad_array", "array shape must be a list of at most 4 ints >= 0")
    if not isinstance(data, bytes):
        raise WireError("bad_array", "array data must be binary")
    dtype = np.dtype(dt)
    if math.prod(shape) * dtype.itemsize != len(data):
        raise WireError("bad_array", f"array of shape {shape} {dt} needs "
                        f"{math.prod(shape) * dtype.itemsize} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _to_wire(value: Any) -> Any:
    np = sys.modules.get("numpy")  # without numpy loaded there are no numpy values
    if np is not None and isinstance(value, np.ndarray):
        return pack_array(value)
    if isinstance(value, dict):
        return {str(k): _to_wire(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_wire(v) for v in value]
    if np is not None and isinstance(value, np.generic):
        return value.item()
    return value


def _from_wire(value: Any, depth: int = 0) -> Any:
    if depth > 16:
        raise WireError("malformed", "message is nested too deeply")
    if isinstance(value, dict):
        if set(value) == {"dtype", "shape", "data"} and isinstance(value.get("data"), bytes):
            return unpack_array(value)
        return {k: _from_wire(v, depth + 1) for k, v in value.items()}
    if isinstance(value, list):
        return [_from_wire(v, depth + 1) for v in value]
    return value


def encode(type_: str, seq: int, fields: dict[str, Any] | None = None, *,
           t_mono_ns: int | None = None) -> bytes:
    """One message as bytes: the envelope plus `fields` (numpy arrays allowed anywhere)."""
    envelope: dict[str, Any] = {
        "v": VERSION, "type": type_, "seq": int(seq),
        "t_mono_ns": time.monotonic_ns() if t_mono_ns is None else int(t_mono_ns),
        "t_wall_ns": time.time_ns(),
    }
    if fields:
        for key, value in fields.items():
            if key in envelope:
                raise ValueError(f"field '{key}' would overwrite the envelope")
            envelope[key] = _to_wire(value)
    return msgpack.packb(envelope, use_bin_type=True)


def unpack_map(data: bytes, max_bytes: int = MAX_MESSAGE_BYTES) -> dict[str, Any]:
    """Bytes to a msgpack map with strict limits; raises WireError, never anything else."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError("malformed", "message must be bytes")
    if len(data) > max_bytes:
        raise WireError("too_large", f"message of {len(data)} bytes exceeds the limit of "
                        f"{max_bytes} bytes")
    keys = _KeyCheck()
    try:
        # map keys of any type decode (`strict_map_key` off), so that the check below names
        # the problem: msgpack's own refusal of an integer key read as garbage
        obj = msgpack.unpackb(bytes(data), raw=False, strict_map_key=False, use_list=True,
                              max_str_len=max_bytes, max_bin_len=max_bytes,
                              max_array_len=max_bytes, max_map_len=max_bytes // 2,
                              max_ext_len=0, ext_hook=_refuse_ext,
                              object_pairs_hook=keys.map)
    except WireError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise WireError("malformed", f"not a msgpack message: {_why(exc)}"
                                     f"{_looks_like_text(bytes(data))}") from None
    if not isinstance(obj, dict):
        raise WireError("malformed", "message must be a msgpack map (send one map of v, type, "
                                     "id, cmd and args per request: docs/protocol.md)")
    if keys.problem is not None:  # the top-level map is the last one decoded
        raise WireError("malformed", keys.problem,
                        None if "id" in keys.last_repeated else obj.get("id"))
    return obj


class _KeyCheck:
    """Maps whose keys are strings, each once: a request with `cmd` twice ran the second
    (a proxy that reads the first would see another command), and a bytes key was taken
    where an integer one was refused. The first problem is kept, not raised, so the
    message still decodes and its reply can echo the request's `id` (unless `id` itself
    was repeated: then no one id is the request's)."""

    def __init__(self) -> None:
        self.problem: str | None = None
        self.last_repeated: set[str] = set()
        """The keys the map decoded last repeated (msgpack decodes inner maps first)."""

    def map(self, pairs: list[tuple[Any, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        self.last_repeated = set()
        for key, value in pairs:
            if not isinstance(key, str):
                self._note(f"map keys must be strings, got {type(key).__name__}")
            elif key in out:
                self._note(f"a map repeats the key '{key[:64]}'")
                self.last_repeated.add(key)
            else:
                out[key] = value
        return out

    def _note(self, problem: str) -> None:
        if self.problem is None:
            self.problem = problem


def _why(exc: Exception) -> str:
    """What is wrong with bytes msgpack refused, in words rather than the exception's
    class name."""
    if isinstance(exc, msgpack.ExtraData):
        if not isinstance(exc.unpacked, dict):  # b"hello" reads as the int 104, then "ello"
            return (f"it begins with a msgpack {type(exc.unpacked).__name__} where a map "
                    f"should be, and {len(exc.extra)} bytes follow it")
        return f"{len(exc.extra)} bytes left over after the message's map"
    if isinstance(exc, UnicodeDecodeError):
        return "a string that is not UTF-8"
    if isinstance(exc, msgpack.StackError):
        return "nested too deep"
    if "ext" in str(exc):
        return "msgpack extension types are not allowed"
    if isinstance(exc, ValueError) and "exceeds" in str(exc):
        return "a string, array or map longer than the message allows"
    return "the bytes end early or hold an invalid msgpack type"


def _looks_like_text(data: bytes) -> str:
    """A hint when the bytes are printable text: JSON or a typed command reads as msgpack
    integers and strings, and the refusal's words alone puzzled a held-out client."""
    head = data[:64]
    if head and all(32 <= b < 127 or b in b"\t\r\n" for b in head):
        return (" (the bytes are text: a request is one msgpack map, not JSON or words; "
                "docs/protocol.md)")
    return ""


def _refuse_ext(code: int, data: bytes) -> Any:
    raise WireError("malformed", f"msgpack extension type {code} is not allowed")


def check_envelope(obj: dict[str, Any], *, need_seq: bool = True,
                   versions: tuple[int, ...] = (VERSION,)) -> None:
    """Raise WireError unless `obj` carries a valid envelope of our version (or one of
    `versions`)."""
    v = obj.get("v")
    if type(v) is not int or v not in versions:  # `true` and `2.0` are not version 2
        said = "carries no schema version" if v is None else f"has schema version {v!r}"
        raise WireError("bad_version", f"the message {said}, which is not supported: this "
                        f"service speaks protocol version {VERSION} only (v={VERSION}); "
                        f"update the client to version {VERSION} (docs/protocol.md: `state` "
                        "carries per-finger `fingers` instead of `centre`) and send "
                        f"v={VERSION}")
    if not isinstance(obj.get("type"), str):
        raise WireError("malformed", "envelope field 'type' must be a string")
    if need_seq:
        for key in ("seq", "t_mono_ns", "t_wall_ns"):
            if not isinstance(obj.get(key), int) or isinstance(obj.get(key), bool):
                raise WireError("malformed", f"envelope field '{key}' must be an integer")


def decode(data: bytes, max_bytes: int = MAX_FRAME_BYTES, topic: str = "",
           versions: tuple[int, ...] = (VERSION,)) -> Message:
    """Bytes from the stream to a Message (arrays as read-only numpy arrays)."""
    obj = unpack_map(data, max_bytes)
    check_envelope(obj, versions=versions)
    body = {k: _from_wire(v) for k, v in obj.items()
            if k not in ("v", "type", "seq", "t_mono_ns", "t_wall_ns")}
    return Message(type=obj["type"], seq=obj["seq"], t_mono_ns=obj["t_mono_ns"],
                   t_wall_ns=obj["t_wall_ns"], body=body, topic=topic)


def decode_fields(value: Any) -> Any:
    """Arrays in an already unpacked value (command arguments and results) to numpy."""
    return _from_wire(value)
