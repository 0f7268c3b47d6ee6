"""Typed protocol requests: every op decodes, every documented error gives its code and names the field, hostile
input (NaN, huge arrays, deep nesting, random and mutated bytes) never raises anything but a RequestError."""

from __future__ import annotations

import math
import pickle

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.clip import clip_from_dict
from models.protocol import ProtocolError
from runtime import messages as M
from runtime.messages import RequestError, decode_request

CLIP = {"name": "hi", "channels": {
    "jaw": {"interp": "linear", "keys": [[0, 0], [0.5, 15], [1.0, 0]]},
    "blink": {"interp": "step", "keys": [[0, 0], [0.4, 40], [0.55, 0]]},
    "brow_l": {"interp": "bezier", "keys": [[0, 0, 0, 0, 0.3, 0], [1.0, 20, -0.3, 0, 0, 0]]}}}

VALID = [
    ({"op": "hello", "id": 1}, M.HelloRequest),
    ({"op": "hello", "id": "a", "client": "studio"}, M.HelloRequest),
    ({"op": "hello", "client": 5}, M.HelloRequest),  # never checked: kept so
    ({"op": "status", "id": 2}, M.StatusRequest),
    ({"op": "enable", "id": 3}, M.EnableRequest),
    ({"op": "disable"}, M.DisableRequest),
    ({"op": "estop", "id": 9, "reason": "stage manager"}, M.EStopRequest),
    ({"op": "reset", "id": 10}, M.ResetRequest),
    ({"op": "clock", "id": 11, "t_client": 5021.25}, M.ClockRequest),
    ({"op": "load_clip", "id": 4, "clip": CLIP}, M.LoadClipRequest),
    ({"op": "unload_clip", "id": 4, "clip": "hi"}, M.UnloadClipRequest),
    ({"op": "play", "id": 5, "clip": "hi", "at": 1240.0, "loop": False, "speed": 1.0, "from": 0.5}, M.PlayRequest),
    ({"op": "pause"}, M.PauseRequest),
    ({"op": "resume"}, M.ResumeRequest),
    ({"op": "stop"}, M.StopMotionRequest),
    ({"op": "seek", "id": 6, "time": 0.25}, M.SeekRequest),
    ({"op": "stream", "id": 7, "channels": ["jaw", "blink"], "frames": [[1250.0, 5.0, 0.0], [1250.01, 5.4, 0]]},
     M.StreamRequest),
    ({"op": "pose", "id": 8, "pose": {"jaw": 10.0, "blink": 20}}, M.PoseRequest),
    ({"op": "record", "id": 12, "action": "start", "name": "take1"}, M.RecordRequest),
    ({"op": "record", "id": 13, "action": "stop"}, M.RecordRequest),
]


def _decode(msg: object) -> M.Request:
    return decode_request(msgpack.packb(msg, use_bin_type=True))


def _error(msg: object) -> RequestError:
    with pytest.raises(RequestError) as info:
        _decode(msg)
    return info.value


@pytest.mark.parametrize(("msg", "kind"), VALID, ids=[f"{m['op']}-{i}" for i, (m, _) in enumerate(VALID)])
def test_every_op_decodes_to_its_struct(msg: dict, kind: type) -> None:
    req = _decode(msg)
    assert type(req) is kind
    assert req.id == msg.get("id")


def test_every_op_has_a_schema_and_the_ops_are_the_documented_ones() -> None:
    assert set(M.OPS) == {"hello", "status", "enable", "disable", "estop", "reset", "clock", "load_clip",
                          "unload_clip", "play", "pause", "resume", "stop", "seek", "stream", "pose", "record"}


def test_defaults_and_decoded_values() -> None:
    play = _decode({"op": "play", "clip": "hi", "speed": None})
    assert (play.at, play.from_, play.speed, play.loop) == (None, 0.0, 1.0, False)
    assert _decode({"op": "estop"}).reason == "api"
    assert _decode({"op": "record", "action": "start"}).name == "recording"
    stream = _decode(VALID[16][0])
    arr = stream.array()
    assert arr.shape == (2, 3) and arr.dtype == np.float64 and not arr.flags.writeable
    assert arr[1].tolist() == [1250.01, 5.4, 0.0]
    pose = _decode(VALID[17][0])
    assert pose.pose == {"jaw": 10.0, "blink": 20.0} and pose.speed is None


@pytest.mark.parametrize("channels", [1, 14, 15, 52])
@pytest.mark.parametrize("frames", [1, 15, 16, 2000])
def test_float64_frames_read_from_the_bytes_equal_the_general_decode(channels: int, frames: int) -> None:
    rng = np.random.default_rng(frames + channels)
    values = rng.uniform(-30, 30, (frames, channels + 1))
    names = [f"c{i}" for i in range(channels)]
    floats = msgpack.packb({"op": "stream", "channels": names, "frames": values.tolist()})
    mixed = values.tolist()
    mixed[-1][-1] = 7  # one integer: not the all-float64 layout
    fast, slow = decode_request(floats).array(), decode_request(msgpack.packb(
        {"op": "stream", "channels": names, "frames": mixed})).array()
    assert np.array_equal(fast, values)
    assert np.array_equal(slow[:-1], values[:-1]) and slow[-1, -1] == 7.0
    single = decode_request(msgpack.packb({"op": "stream", "channels": names, "frames": values.tolist()},
                                          use_single_float=True)).array()
    assert np.array_equal(single, values.astype(np.float32))
    values[-1, 0] = np.nan
    err = _error({"op": "stream", "channels": names, "frames": values.tolist()})
    assert err.code == "bad_value" and f"frames[{frames - 1}][0]" in err.message
    err = _error({"op": "stream", "channels": names, "frames": [*values[:-1].tolist(), values[-1, :-1].tolist()]})
    assert err.code == "bad_request" and f"frames[{frames - 1}]" in err.message


def test_clip_spec_matches_the_clip_parser() -> None:
    spec = _decode({"op": "load_clip", "clip": CLIP}).clip
    clip = clip_from_dict(CLIP)
    assert spec.duration == clip.duration and spec.key_count() == clip.key_count()
    assert spec.key_array("brow_l").shape == (2, 6)
    ref = spec.to_clip()
    for t in np.linspace(-0.5, 1.5, 41):
        assert ref.sample(t) == clip.sample(t)


def test_decoded_requests_pickle() -> None:
    req = _decode({"op": "load_clip", "id": 4, "clip": CLIP})
    back = pickle.loads(pickle.dumps(req))
    assert back == req and np.array_equal(back.clip.key_array("jaw"), req.clip.key_array("jaw"))


ERRORS = [
    # not a map, op missing or mistyped, unknown op
    ([1, 2], "bad_request", "map"),
    ("hello", "bad_request", "map"),
    ({"id": 1}, "bad_request", "'op'"),
    ({"op": 3}, "bad_request", "'op'"),
    ({"op": "dance"}, "unknown_op", "known: clock"),
    # the id
    ({"op": "hello", "id": True}, "bad_request", "'id'"),
    ({"op": "hello", "id": "x" * 129}, "bad_request", "'id'"),
    ({"op": "hello", "id": 1.5}, "bad_request", "'id'"),
    ({"op": "hello", "id": None}, "bad_request", "'id'"),  # absent is fine, an explicit null is not
    ({"op": "dance", "id": {}}, "bad_request", "'id'"),  # a malformed id is reported before the op
    # unknown fields
    ({"op": "status", "verbose": True}, "bad_request", "unknown field 'verbose' for op 'status'"),
    ({"op": "play", "clip": "a", "sped": 2}, "bad_request", "allowed: at, clip, from, loop, speed"),
    # missing and mistyped fields
    ({"op": "play"}, "bad_request", "'clip' is required"),
    ({"op": "play", "clip": 3}, "bad_request", "'clip' must be a string"),
    ({"op": "play", "clip": ""}, "bad_request", "'clip'"),
    ({"op": "play", "clip": "a", "loop": 1}, "bad_request", "'loop' must be true or false"),
    ({"op": "play", "clip": "a", "speed": "fast"}, "bad_request", "'speed' must be a number"),
    ({"op": "seek"}, "bad_request", "'time' is required"),
    ({"op": "seek", "time": None}, "bad_request", "'time'"),
    ({"op": "estop", "reason": ""}, "bad_request", "'reason'"),
    ({"op": "load_clip", "clip": "hi"}, "bad_request", "'clip' must be a map"),
    ({"op": "load_clip"}, "bad_request", "'clip' is required"),
    ({"op": "unload_clip"}, "bad_request", "'clip' is required"),
    ({"op": "stream", "channels": [], "frames": []}, "bad_request", "'channels'"),
    ({"op": "stream", "channels": ["jaw", 3], "frames": []}, "bad_request", "channels[1]"),
    ({"op": "stream", "channels": ["jaw", "jaw"], "frames": []}, "bad_request", "twice"),
    ({"op": "stream", "channels": ["jaw"], "frames": [[1.0]]}, "bad_request", "frames[0] must be [t, 1 values]"),
    ({"op": "stream", "channels": ["jaw"], "frames": [5]}, "bad_request", "frames[0]"),
    ({"op": "stream", "channels": ["jaw"], "frames": [[1, 2], [1, "x"]]}, "bad_value", "frames[1][1]"),
    ({"op": "pose", "pose": {}}, "bad_request", "'pose'"),
    ({"op": "pose", "pose": []}, "bad_request", "'pose' must be a map"),
    ({"op": "pose", "pose": {1: 2.0}}, "bad_request", "pose"),
    ({"op": "pose", "pose": {"nose": 1.0, "jaw": "x"}}, "bad_value", "pose['jaw']"),
    ({"op": "record"}, "bad_request", "'action' is required"),
    ({"op": "record", "action": 1}, "bad_request", "'action'"),
    # out of range
    ({"op": "play", "clip": "a", "speed": 20}, "bad_value", "'speed' must be a finite number <= 10"),
    ({"op": "play", "clip": "a", "speed": 0}, "bad_value", "'speed' must be a finite number >= 0.01"),
    ({"op": "play", "clip": "a", "from": -4000}, "bad_value", "'from'"),
    ({"op": "seek", "time": 1e9}, "bad_value", "'time'"),
    ({"op": "pose", "pose": {"jaw": 1.0}, "speed": 2}, "bad_value", "'speed'"),
    ({"op": "record", "action": "pause"}, "bad_value", "must be one of start, stop"),
    ({"op": "record", "action": "start", "name": "../etc"}, "bad_value", "record name"),
    # malformed clips are bad values, naming the clip, channel and key
    ({"op": "load_clip", "clip": {"channels": {"jaw": {"keys": [[0, 0]]}}}}, "bad_value", "'clip.name' is required"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"keys": [[0, 0]]}}, "x": 1}}, "bad_value",
     "unknown field 'x' in 'clip'"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {}}}, "bad_value", "clip.channels"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"keys": []}}}}, "bad_value", "jaw"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"a": {"keys": [[0, 0]]},
                                                            "jaw": {"keys": [[0, 0]], "interp": "cubic"}}}},
     "bad_value", "'clip.channels.jaw.interp' must be one of step, linear, bezier"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"a": {"keys": [[0, 0]]}, "jaw": {"keys": [[0, 0]],
                                                                                            "bogus": 1}}}},
     "bad_value", "unknown field 'bogus' in 'clip.channels.jaw'"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"a": {"keys": [[0, 0]]}, "jaw": {"interp": "step"}}}},
     "bad_value", "'clip.channels.jaw.keys' is required"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"a": {"keys": [[0, 0]]}, "jaw": 5}}},
     "bad_value", "'clip.channels.jaw' must be a map"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"a": {"keys": [[0, 0]]}, "jaw": {"keys": [[0, "x"]]}}}},
     "bad_value", "channels.jaw.keys[0][1] must be a number"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"keys": [[0, 0], [0, 1]]}}}},
     "bad_value", "clip 'c'.channels.jaw.keys[1]: times must increase strictly"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"keys": [[0, 0, 1]]}}}},
     "bad_value", "jaw.keys[0] must be a list of 2 numbers for linear"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"interp": "bezier",
                                                                      "keys": [[0, 0, 0.1, 0, 0, 0]]}}}},
     "bad_value", "need in_dt <= 0 <= out_dt"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"": {"keys": [[0, 0]]}}}}, "bad_value", "clip.channels"),
]


@pytest.mark.parametrize(("msg", "code", "fragment"), ERRORS)
def test_documented_errors_give_their_code_and_name_the_field(msg: object, code: str, fragment: str) -> None:
    err = _error(msg)
    assert err.code == code, err.message
    assert fragment in err.message


@pytest.mark.parametrize("op", sorted(M.OPS))
def test_unknown_fields_are_refused_for_every_op(op: str) -> None:
    err = _error({"op": op, "id": 77, "surprise": 1})
    assert (err.code, err.request_id) == ("bad_request", 77)
    assert "surprise" in err.message


NONFINITE = [
    ({"op": "clock", "t_client": math.nan}, "t_client"),
    ({"op": "play", "clip": "a", "at": math.inf}, "at"),
    ({"op": "play", "clip": "a", "from": math.nan}, "from"),
    ({"op": "play", "clip": "a", "speed": math.nan}, "speed"),
    ({"op": "seek", "time": -math.inf}, "time"),
    ({"op": "pose", "pose": {"jaw": 1.0}, "speed": math.nan}, "speed"),
    ({"op": "pose", "pose": {"jaw": math.inf}}, "pose['jaw']"),
    ({"op": "stream", "channels": ["jaw", "blink"], "frames": [[0, 1, 2], [1, 2, math.nan]]}, "frames[1][2]"),
    ({"op": "stream", "channels": ["jaw"], "frames": [[math.inf, 1]]}, "frames[0][0]"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"keys": [[0, 0], [1, math.nan]]}}}},
     "jaw.keys[1][1]"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"interp": "bezier", "keys": [
        [0, 0, 0, 0, math.inf, 0]]}}}}, "jaw.keys[0][4]"),
]


@pytest.mark.parametrize(("msg", "field"), NONFINITE)
def test_nan_and_infinity_are_bad_values_naming_the_field(msg: dict, field: str) -> None:
    err = _error(msg)
    assert err.code == "bad_value" and field in err.message and "finite" in err.message


@pytest.mark.parametrize(("msg", "fragment"), [
    ({"op": "stream", "channels": ["jaw"], "frames": [[0.0, 1.0]] * (M.MAX_STREAM_FRAMES + 1)}, "'frames'"),
    ({"op": "stream", "channels": [f"c{i}" for i in range(257)], "frames": []}, "'channels'"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {f"c{i}": {"keys": [[0, 0]]} for i in range(257)}}},
     "clip.channels"),
    ({"op": "load_clip", "clip": {"name": "c", "channels": {
        "a": {"keys": [[i, 0] for i in range(100_001)]}, "b": {"keys": [[i, 0] for i in range(100_000)]}}}},
     "200001 keys"),
])
def test_arrays_over_their_limit_are_too_large(msg: dict, fragment: str) -> None:
    err = _error(msg)
    assert err.code == "too_large" and fragment in err.message


def _nested(levels: int, inner: bytes = b"\x01") -> bytes:
    return b"\x91" * levels + inner


def _packed_map(*items: tuple[str, bytes]) -> bytes:
    return bytes([0x80 | len(items)]) + b"".join(msgpack.packb(k) + v for k, v in items)


@pytest.mark.parametrize("levels", [40, 1_000, 100_000])
def test_deep_nesting_is_a_bad_request_not_a_recursion_error(levels: int) -> None:
    clip = msgpack.packb({"name": "c", "channels": {"jaw": {"keys": [[0, 0]]}}})
    clip_with_meta = bytes([clip[0] + 1]) + clip[1:] + msgpack.packb("meta") + _nested(levels)
    cases = [
        _packed_map(("id", msgpack.packb(5)), ("op", msgpack.packb("load_clip")), ("clip", clip_with_meta)),
        _packed_map(("id", msgpack.packb(5)), ("junk", _nested(levels)), ("op", msgpack.packb("hello"))),
        _packed_map(("id", msgpack.packb(5)), ("op", msgpack.packb("stream")), ("channels", _nested(levels))),
        _packed_map(("id", msgpack.packb(5)), ("op", msgpack.packb("hello")), ("client", _nested(levels))),
    ]
    for raw in cases:
        with pytest.raises(RequestError) as info:
            decode_request(raw)
        assert info.value.code == "bad_request" and info.value.request_id == 5
    with pytest.raises(RequestError) as info:
        decode_request(_nested(levels))
    assert info.value.code == "bad_request"


def test_meta_nesting_up_to_the_bound_is_accepted() -> None:
    meta: object = 1
    for _ in range(M.MAX_DEPTH - 3):  # request map, clip map, then meta's containers
        meta = [meta]
    req = _decode({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"keys": [[0, 0]]}}, "meta": meta}})
    assert req.clip.meta is not None
    with pytest.raises(RequestError, match="nested deeper"):
        _decode({"op": "load_clip", "clip": {"name": "c", "channels": {"jaw": {"keys": [[0, 0]]}}, "meta": [[meta]]}})


def test_request_id_survives_every_failure() -> None:
    assert _error({"op": "play", "id": "req-9", "clip": "a", "speed": 99}).request_id == "req-9"
    assert _error({"id": 2**64 - 1, "op": "dance"}).request_id == 2**64 - 1
    assert _error({"op": "stream", "id": -5, "channels": ["a"], "frames": [[0, math.nan]]}).request_id == -5
    assert _error({"op": "hello", "id": [1]}).request_id is None  # not a valid id: echoed as null
    with pytest.raises(RequestError) as info:
        decode_request(b"\xc1")
    assert info.value.code == "bad_request" and info.value.request_id is None
    assert isinstance(info.value, ProtocolError)


# ----------------------------------------------------------------------------------------------- fuzz
NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.integers(min_value=-(2**63), max_value=2**64 - 1),
                    st.sampled_from([0.0, 1e308, -1e308, 1e-320, 28.0, -2.0, 45.0]))
SCALARS = st.one_of(st.none(), st.booleans(), NUMBERS, st.text(max_size=20), st.binary(max_size=20))
ANY = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=8), inner, max_size=5)), max_leaves=20)
KEYS = st.lists(st.lists(NUMBERS, min_size=0, max_size=7), max_size=6)
CLIPS = st.fixed_dictionaries({
    "name": st.one_of(st.text(max_size=10), ANY),
    "channels": st.dictionaries(st.sampled_from(["jaw", "blink", "", "x" * 200]), st.fixed_dictionaries(
        {"keys": st.one_of(KEYS, ANY)}, optional={"interp": st.sampled_from(["step", "linear", "bezier", "x"])}),
        max_size=4),
}, optional={"meta": ANY})
FIELDS = st.dictionaries(
    st.sampled_from(["clip", "at", "from", "speed", "loop", "time", "channels", "frames", "pose", "reason",
                     "action", "name", "t_client", "client", "bogus"]),
    st.one_of(ANY, CLIPS, st.sampled_from(["probe", "start", "stop"]), KEYS,
              st.dictionaries(st.sampled_from(["jaw", "blink", ""]), NUMBERS, max_size=4),
              st.lists(st.sampled_from(["jaw", "blink", ""]), max_size=4)),
    max_size=4)
REQUESTS = st.one_of(ANY, st.builds(
    lambda op, rid, f: {"op": op, "id": rid, **f}, st.sampled_from([*M.OPS, "dance", ""]),
    st.one_of(st.integers(min_value=-(2**63), max_value=2**64 - 1), st.text(max_size=200), ANY), FIELDS))


def _only_request_errors(raw: bytes) -> None:
    try:
        req = decode_request(raw)
    except RequestError as exc:
        assert exc.code in ("bad_request", "unknown_op", "bad_value", "too_large"), exc.code
        assert exc.message and len(exc.message) < 2000
        assert exc.request_id is None or isinstance(exc.request_id, int | str)
        msgpack.packb({"id": exc.request_id, "error": exc.message})  # always sendable
    else:
        assert type(req) in M.OP_TYPES.values()


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(msg=REQUESTS)
def test_random_requests_never_raise_anything_but_request_errors(msg: object) -> None:
    _only_request_errors(msgpack.packb(msg, use_bin_type=True))


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(base=st.sampled_from([m for m, _ in VALID]), data=st.data())
def test_mutated_valid_requests_never_raise_anything_but_request_errors(base: dict, data: st.DataObject) -> None:
    raw = bytearray(msgpack.packb(base, use_bin_type=True))
    for _ in range(data.draw(st.integers(1, 4))):
        kind = data.draw(st.sampled_from(["flip", "insert", "delete", "truncate"]))
        pos = data.draw(st.integers(0, len(raw)))
        if kind == "flip" and pos < len(raw):
            raw[pos] = data.draw(st.integers(0, 255))
        elif kind == "insert":
            raw[pos:pos] = data.draw(st.binary(min_size=1, max_size=4))
        elif kind == "delete" and pos < len(raw):
            del raw[pos]
        elif kind == "truncate":
            del raw[pos:]
    _only_request_errors(bytes(raw))
