"""The exact FEM pose in its worker process, against the predictor (slow: the FEM kernels compile first)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.studio.conftest import SAMPLE


@pytest.mark.slow
def test_exact_pose_in_a_worker_agrees_with_the_predictor_within_its_error_scale() -> None:
    from studio.fem_worker import ExactPoser
    from studio.head import StudioHead
    from studio.skin import SkinView

    head = StudioHead.load(SAMPLE)
    p = head.apply(head.neutral, {"jaw": 5.0})
    poser = ExactPoser(SAMPLE)
    try:
        exact, converged, iterations = poser.submit(p).result(timeout=600)
    finally:
        poser.close()
    assert converged and iterations >= 1 and exact.shape == (head.predictor.n_vertices, 3)
    bands, worst, mean = SkinView(head).error_bands(exact, head.predictor.predict(p))
    assert mean < 1.0 and worst < 4.0  # the predictor's documented accuracy on the sample head
    assert sum(len(b) for b in bands) == len(head.predictor.faces)
    assert np.abs(exact - head.predictor.base_vertices).max() > 1e-3  # the FEM moved the skin
