"""A predictor built without its onnxruntime session (as the control loop builds it) reads the same model, loads the
session on its first full pass, and refuses a corrupt file at construction as the eager one does; the in-cycle kernels
compiled ahead of time give the JIT's results."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from models.errors import SpecError
from models.kernel_support import kernels_available
from models.onnx_tensors import read_model_info
from models.predictor import SkinPredictor

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample"


def test_lazy_predictor_reads_the_same_model_and_predicts_on_demand() -> None:
    eager = SkinPredictor(SAMPLE / "predictor.onnx")
    lazy = SkinPredictor(SAMPLE / "predictor.onnx", session=False)
    assert lazy._session_obj is None
    assert dict(lazy.metadata) == dict(eager.metadata)
    assert lazy.actuator_names == eager.actuator_names
    np.testing.assert_array_equal(lazy.base_vertices, eager.base_vertices)
    np.testing.assert_array_equal(lazy.weights.W1[0], eager.weights.W1[0])
    p = 0.5 * (eager.lo + eager.hi)
    np.testing.assert_array_equal(lazy.predict(p), eager.predict(p))  # the session, loaded now
    assert lazy._session_obj is not None
    out = np.empty((eager.n_vertices, 3), dtype=np.float32)
    np.testing.assert_array_equal(lazy.predict(p, out=out), eager.predict(p))  # the bound one-pose path


def test_model_info_matches_onnxruntime() -> None:
    import onnxruntime as ort

    inputs, outputs, meta = read_model_info(SAMPLE / "predictor.onnx")
    s = ort.InferenceSession(str(SAMPLE / "predictor.onnx"), providers=["CPUExecutionProvider"])
    assert {i.name for i in s.get_inputs()} <= set(inputs)
    assert [o.name for o in s.get_outputs()] == list(outputs)
    assert meta == dict(s.get_modelmeta().custom_metadata_map)


@pytest.mark.parametrize("content", [b"\x00\x01\x02garbage" * 50, b"", None])
def test_corrupt_model_is_refused_at_construction(tmp_path: Path, content: bytes | None) -> None:
    path = tmp_path / "predictor.onnx"
    data = (SAMPLE / "predictor.onnx").read_bytes()
    path.write_bytes(data[: len(data) // 3] if content is None else content)  # None: truncated
    with pytest.raises(SpecError) as info:
        SkinPredictor(path, session=False)
    assert str(path) in str(info.value)


@pytest.mark.skipif(not kernels_available(), reason="numba is not installed")
def test_ahead_of_time_kernels_match_the_jit() -> None:
    from models.kernels import warm
    from models.kernels_aot import EXPORTS, jit, kernel, module, recording

    warm(str(SAMPLE / "head.toml"))
    assert module() is not None
    examples: dict[str, tuple] = {}
    with recording(examples):  # the arguments a head's solver and guard pass
        warm(str(SAMPLE / "head.toml"), ahead_of_time=False)
    assert set(EXPORTS) <= set(examples)
    for name in EXPORTS:
        args_jit = tuple(a.copy() if isinstance(a, np.ndarray) else a for a in examples[name])
        args_aot = tuple(a.copy() if isinstance(a, np.ndarray) else a for a in examples[name])
        fn = kernel(name)
        assert fn is not jit(name)
        got, ref = fn(*args_aot), jit(name)(*args_jit)
        got, ref = (() if x is None else x if isinstance(x, tuple) else (x,) for x in (got, ref))
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_allclose(g, r, rtol=1e-12, atol=1e-15)
        for a, b in zip(args_aot, args_jit, strict=True):  # buffers written alike
            if isinstance(a, np.ndarray):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
    assert "numba" in sys.modules  # this process ran the JIT for the comparison
