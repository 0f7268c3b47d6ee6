"""Compiled clips sample like ``Clip.sample`` (all three interpolations, random clips), hold outside their keys, keep
NaN for channels without a curve, pickle, and stay small; stream requests become frame batches."""

from __future__ import annotations

import itertools
import pickle

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.clip import Clip, ClipError, clip_from_dict
from models.kernel_support import kernels_available
from runtime.compiled import CompiledClip, compile_clip
from runtime.messages import decode_request

FINITE = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False)


@st.composite
def channel_specs(draw: st.DrawFn) -> dict:
    interp = draw(st.sampled_from(["step", "linear", "bezier"]))
    n = draw(st.integers(1, 8))
    start = draw(st.floats(-50, 50))
    steps = draw(st.lists(st.floats(1e-4, 5.0), min_size=n - 1, max_size=n - 1))
    times = np.cumsum([start, *steps]).tolist()
    keys = []
    for t in times:
        v = draw(FINITE)
        if interp == "bezier":
            keys.append([t, v, -draw(st.floats(0, 6)), draw(FINITE), draw(st.floats(0, 6)), draw(FINITE)])
        else:
            keys.append([t, v])
    return {"interp": interp, "keys": keys}


CLIPS = st.builds(lambda chans: {"name": "c", "channels": chans},
                  st.dictionaries(st.sampled_from(["jaw", "blink", "brow_l", "lid_r", "nose"]), channel_specs(),
                                  min_size=1, max_size=5))
COLUMNS = ["nose", "jaw", "cheek_r", "blink", "brow_l", "lid_r"]  # cheek_r never has a curve


def _reference(clip: Clip, t: float) -> np.ndarray:
    values = clip.sample(t)
    return np.array([values.get(ch, np.nan) for ch in COLUMNS])


def _probe_times(clip: Clip, extra: list[float]) -> list[float]:
    keys = sorted({k for c in clip.channels.values() for k in c.times})
    mids = [(a + b) / 2 for a, b in itertools.pairwise(keys)]
    return [*keys, *mids, keys[0] - 1.0, keys[-1] + 1.0, *extra]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=CLIPS, extra=st.lists(st.floats(-60, 90), max_size=20))
def test_compiled_clip_equals_clip_sample(data: dict, extra: list[float]) -> None:
    clip = clip_from_dict(data)
    spec = decode_request(msgpack.packb({"op": "load_clip", "clip": data})).clip
    compiled = [compile_clip(clip, COLUMNS), compile_clip(spec, COLUMNS)]
    key_values = np.array([v for c in clip.channels.values() for v in c.values])
    out, lockstep = np.empty(len(COLUMNS)), np.empty(len(COLUMNS))
    for t in _probe_times(clip, extra):
        ref = _reference(clip, t)
        scale = max(np.ptp(np.append(key_values, ref[np.isfinite(ref)])), 1e-300)
        for cc in compiled:
            out.fill(123.0)
            cc.sample(t, out)
            assert np.array_equal(np.isnan(out), np.isnan(ref))
            ok = np.isfinite(ref)
            assert np.all(np.abs(out[ok] - ref[ok]) <= 1e-9 * scale), (t, out, ref)
            cc.sample(t, lockstep, compiled=False)  # the numpy iteration: the same bits as the kernel
            assert np.array_equal(out, lockstep, equal_nan=True), (t, out, lockstep)
    assert compiled[0].duration == compiled[1].duration == clip.duration
    assert compiled[0].key_count == clip.key_count()


def test_holds_outside_the_keys_and_interpolates_inside() -> None:
    clip = clip_from_dict({"name": "c", "channels": {
        "jaw": {"interp": "linear", "keys": [[1, 10], [2, 20]]},
        "blink": {"interp": "step", "keys": [[0, 5], [1, 7], [3, 9]]},
        "brow_l": {"interp": "bezier", "keys": [[0, 0, 0, 0, 1 / 3, 10 / 3], [1, 10, -1 / 3, -10 / 3, 0, 0]]}}})
    cc = compile_clip(clip, ["jaw", "blink", "brow_l", "nose"])
    out = np.empty(4)
    cc.sample(-5.0, out)
    assert out[:3].tolist() == [10.0, 5.0, 0.0] and np.isnan(out[3])
    cc.sample(1.5, out)
    assert out[0] == 15.0 and out[1] == 7.0 and out[2] == 10.0
    cc.sample(0.5, out)
    assert out[0] == 10.0 and out[1] == 5.0 and out[2] == pytest.approx(5.0, abs=1e-6)
    cc.sample(3.0, out)
    assert out[:3].tolist() == [20.0, 9.0, 10.0]
    cc.sample(1e6, out)
    assert out[:3].tolist() == [20.0, 9.0, 10.0]
    assert cc.channel_index == ("jaw", "blink", "brow_l", "nose") and cc.duration == 3.0
    with pytest.raises(ValueError, match="4 channels"):
        cc.sample(0.5, np.empty(3))


def test_channels_outside_the_columns_or_listed_twice_are_refused() -> None:
    clip = clip_from_dict({"name": "c", "channels": {"jaw": {"keys": [[0, 0]]}, "ghost": {"keys": [[0, 1]]}}})
    with pytest.raises(ClipError, match="ghost"):
        compile_clip(clip, ["jaw", "blink"])
    with pytest.raises(ClipError, match="twice"):
        compile_clip(clip, ["jaw", "ghost", "jaw"])


def test_compiled_clip_pickles_and_is_read_only() -> None:
    clip = clip_from_dict({"name": "c", "channels": {
        "jaw": {"interp": "bezier", "keys": [[0, 0, 0, 0, 0.2, 3], [1, 10, -0.5, 1, 0.1, 0], [2, 4, 0, 0, 0, 0]]},
        "blink": {"keys": [[0, 1], [2, 3]]}}})
    cc = compile_clip(clip, ["blink", "jaw"])
    back = pickle.loads(pickle.dumps(cc))
    assert isinstance(back, CompiledClip)
    a, b = np.empty(2), np.empty(2)
    for t in np.linspace(-1, 3, 57):
        cc.sample(t, a)
        back.sample(t, b)
        assert np.array_equal(a, b)
    with pytest.raises(ValueError):
        cc.slot_v[1] = 0.0


def _bezier_clip(seed: int, channels: int = 12, keys: int = 30) -> Clip:
    rng = np.random.default_rng(seed)
    out = {}
    for c in range(channels):
        t, v = np.cumsum(rng.uniform(0.05, 1.0, keys)), rng.normal(0, 10, keys)
        out[f"c{c}"] = {"interp": "bezier", "keys": [
            [t[j], v[j], -rng.uniform(0, 0.6), rng.normal(), rng.uniform(0, 0.6), rng.normal()] for j in range(keys)]}
    return clip_from_dict({"name": "b", "channels": out})


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.skipif(
    not kernels_available(), reason="numba is not installed"))])
def test_bezier_channels_keep_the_bits_of_clip_sample(compiled: bool) -> None:
    clip = _bezier_clip(5)
    cols = list(clip.channels)
    cc, out = compile_clip(clip, cols), np.empty(len(cols))
    for t in np.random.default_rng(6).uniform(-1.0, clip.duration + 1.0, 1500):
        cc.sample(t, out, compiled=compiled)
        values = clip.sample(t)
        assert out.tolist() == [values[c] for c in cols], t


@pytest.mark.skipif(not kernels_available(), reason="numba is not installed")
def test_the_bezier_kernel_is_built_for_the_types_a_clip_passes() -> None:
    from numba import typeof

    from models.kernel_args import bezier_sample_example
    from models.kernels_aot import recording

    for spec in (False, True):  # a Clip and a validated ClipSpec compile to the same array types
        data = {"name": "b", "channels": {"jaw": {"interp": "bezier", "keys": [
            [0, 0, 0, 0, 0.2, 3], [1, 10, -0.5, 1, 0.1, 0]]}, "blink": {"keys": [[0, 1], [2, 3]]}}}
        clip = decode_request(msgpack.packb({"op": "load_clip", "clip": data})).clip if spec else clip_from_dict(data)
        examples: dict[str, tuple] = {}
        with recording(examples):
            compile_clip(clip, ["blink", "jaw"]).sample(0.5, np.empty(2), compiled=True)
        assert [typeof(a) for a in examples["bezier_sample"]] == [typeof(a) for a in bezier_sample_example()]


def test_a_megabyte_clip_compiles_to_a_few_megabytes() -> None:
    rng = np.random.default_rng(3)
    channels = {}
    for c in range(52):
        t = np.cumsum(rng.uniform(0.01, 0.05, 1000))
        channels[f"c{c}"] = {"interp": "linear", "keys": np.column_stack([t, rng.uniform(-30, 30, 1000)]).tolist()}
    raw = msgpack.packb({"op": "load_clip", "clip": {"name": "big", "channels": channels}})
    assert 0.9 * 2**20 < len(raw) <= 2**20
    cc = compile_clip(decode_request(raw).clip, list(channels))
    assert cc.key_count == 52_000
    assert cc.nbytes / cc.key_count <= 56
    assert cc.nbytes <= 3 * len(raw)
