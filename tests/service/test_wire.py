"""The wire format: round trips, and strict refusal of everything else."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from service.wire import envelope as wire

DTYPES = [np.float64, np.float32, np.int64, np.int32, np.uint8, np.bool_]


def test_envelope_round_trip_with_nested_arrays() -> None:
    poses = np.arange(12, dtype=np.float64).reshape(4, 3)
    data = wire.encode("cloud", 7, {"poses": poses, "meta": {"w": np.ones(2, np.float32)},
                                     "n": np.int64(3), "t": (1, 2)})
    msg = wire.decode(data, topic="cloud")
    assert (msg.type, msg.seq, msg.topic) == ("cloud", 7, "cloud")
    assert msg.t_mono_ns > 0 and msg.t_wall_ns > 1_600_000_000 * 10**9
    np.testing.assert_array_equal(msg["poses"], poses)
    assert msg["meta"]["w"].dtype == np.float32
    assert msg["n"] == 3 and msg["t"] == [1, 2]


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(DTYPES).flatmap(
    lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=0, max_dims=3, max_side=5))))
def test_any_numeric_array_survives(a: np.ndarray) -> None:
    back = wire.unpack_array(msgpack.unpackb(msgpack.packb(wire.pack_array(a))))
    assert back.dtype == a.dtype.newbyteorder("<") and back.shape == a.shape
    np.testing.assert_array_equal(back, a)


def test_big_endian_arrays_are_sent_little_endian() -> None:
    a = np.arange(3, dtype=">f8")
    packed = wire.pack_array(a)
    assert packed["dtype"] == "<f8"
    np.testing.assert_array_equal(wire.unpack_array(packed), a)


@pytest.mark.parametrize("data, code", [
    (b"\xc1\xff garbage", "malformed"),
    (msgpack.packb([1, 2, 3]), "malformed"),
    (msgpack.packb(msgpack.ExtType(5, b"x")), "malformed"),
    (b"\x00" * (wire.MAX_MESSAGE_BYTES + 1), "too_large"),
    (msgpack.packb({1: 2}), "malformed"),
    (b"\x81\xc4\x03cmd\xa6status", "malformed"),  # a bytes key was taken as a key
    (b"\x82\xa3cmd\xa6status\xa3cmd\xa8activate", "malformed"),  # `cmd` twice ran the second
    (msgpack.packb({"a": {"b": 1}})[:-1], "malformed"),
])
def test_unpack_refuses_garbage(data: bytes, code: str) -> None:
    with pytest.raises(wire.WireError) as err:
        wire.unpack_map(data)
    assert err.value.code == code
    assert "Error" not in str(err.value)  # words, not an exception's class name


@pytest.mark.parametrize("data, words", [
    (b"hello", "it begins with a msgpack int where a map should be, and 4 bytes follow it"),
    (msgpack.packb({"v": 2}) + b"xy", "2 bytes left over after the message's map"),
    # text, as a held-out JavaScript client sent: msgpack's reading of it is no help alone
    (b'{"cmd": "ping"}', "the bytes are text: a request is one msgpack map, not JSON"),
    (b"status\n", "the bytes are text"),
])
def test_bytes_that_are_not_one_map_are_told_so(data: bytes, words: str) -> None:
    """A C client from the docs: `hello` was answered "bytes left over after the message"
    (msgpack reads 'h' as the int 104, then "ello" is left): true, and no help."""
    with pytest.raises(wire.WireError, match=words):
        wire.unpack_map(data)


@pytest.mark.parametrize(("request_map", "problem", "request_id"), [
    ({"id": "dk", "cmd": "ping", 3: 4}, "map keys must be strings, got int", "dk"),
    ({"id": 7, "args": {b"x": 1}}, "map keys must be strings, got bytes", 7),
])
def test_a_map_with_a_bad_key_is_named_and_keeps_its_request_id(request_map, problem,
                                                                 request_id) -> None:
    """A held-out client got "the bytes end early" for an integer key (msgpack's own
    refusal), and no `id` in the reply though the request's was readable."""
    with pytest.raises(wire.WireError, match=problem) as err:
        wire.unpack_map(msgpack.packb(request_map))
    assert err.value.code == "malformed" and err.value.request_id == request_id


def test_a_repeated_key_keeps_the_request_id_unless_it_is_the_id() -> None:
    with pytest.raises(wire.WireError, match="repeats the key 'cmd'") as err:
        wire.unpack_map(b"\x83\xa2id\xa2dk\xa3cmd\xa4ping\xa3cmd\xa8activate")
    assert err.value.request_id == "dk"
    with pytest.raises(wire.WireError, match="repeats the key 'id'") as err:
        wire.unpack_map(b"\x82\xa2id\x01\xa2id\x02")
    assert err.value.request_id is None


def test_a_repeated_key_is_named_and_nested_maps_are_kept() -> None:
    with pytest.raises(wire.WireError, match="a map repeats the key 'cmd'"):
        wire.unpack_map(b"\x82\xa3cmd\xa6status\xa3cmd\xa8activate")
    nested = {"a": {"b": [1, {"c": 2.5}]}, "d": None}
    assert wire.unpack_map(msgpack.packb(nested)) == nested


def test_bad_envelopes() -> None:
    good = {"v": 2, "type": "state", "seq": 1, "t_mono_ns": 1, "t_wall_ns": 1}
    wire.check_envelope(good)
    for change, code in [({"v": 1}, "bad_version"), ({"v": "2"}, "bad_version"),
                         ({"type": 3}, "malformed"), ({"seq": "x"}, "malformed"),
                         ({"seq": True}, "malformed")]:
        with pytest.raises(wire.WireError) as err:
            wire.check_envelope({**good, **change})
        assert err.value.code == code


@pytest.mark.parametrize("array", [
    {"dtype": "|O", "shape": [1], "data": b"\x00" * 8},
    {"dtype": "<f8", "shape": [2], "data": b"\x00" * 8},
    {"dtype": "<f8", "shape": [-1], "data": b""},
    {"dtype": "<f8", "shape": [1, 1, 1, 1, 1], "data": b"\x00" * 8},
    {"dtype": "<f8", "shape": "1", "data": b"\x00" * 8},
])
def test_bad_arrays_are_refused(array: dict) -> None:
    with pytest.raises(wire.WireError):
        wire.unpack_array(array)


def test_objects_cannot_be_sent() -> None:
    with pytest.raises(wire.WireError):
        wire.pack_array(np.array([object()]))
    with pytest.raises(ValueError):
        wire.encode("state", 1, {"seq": 3})
