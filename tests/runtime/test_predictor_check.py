"""The daemon's start-up check of the skin predictor by onnxruntime (runtime.predictor_check): a model onnxruntime
runs is accepted and remembered by its content (the next start skips the check), one it refuses raises the error
naming the file and is never remembered."""

from __future__ import annotations

from pathlib import Path

import pytest

from models.errors import SpecError
from runtime.predictor_check import PredictorCheck
from tests.runtime.conftest import SAMPLE


def test_accepted_once_then_remembered_and_a_refused_model_never(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LIKENESS_CACHE", str(tmp_path / "cache"))
    good = SAMPLE.parent / "predictor.onnx"
    first = PredictorCheck(good)
    assert not first.cached
    first.result()
    again = PredictorCheck(good)
    assert again.cached
    again.result()
    bad = tmp_path / "predictor.onnx"
    bad.write_bytes(good.read_bytes().replace(b"Tanh", b"Tanx"))  # parses; onnxruntime knows no Tanx
    for _ in range(2):
        check = PredictorCheck(bad)
        assert not check.cached
        with pytest.raises(SpecError, match=r"predictor\.onnx: graph: onnxruntime cannot load the model"):
            check.result()
