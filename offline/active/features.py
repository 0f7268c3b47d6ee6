"""GEN-LAL's features of one candidate pose: the model state (the mesh the current predictor yields for it) and
the candidate's actuator values, plus two scalars of the labelled set.

The predicted mesh is fed to a 1-D CNN, so its vertices are laid out along a locality-preserving curve (Morton
order of the base surface): neighbours in the sequence are mostly neighbours on the face, which is what a
convolution over the sequence needs. The two scalars (log of the labelled-set size, distance from the candidate
to its nearest labelled pose in normalized actuator space) are an addition to the paper's features, as in the
original LAL's model-state features: the value of a sample depends on how much data there already is and how
close it lies to it, and neither can be read off a single predicted mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from offline.active.learner import KsnnState, predict

N_EXTRA = 2


def morton_order(base: np.ndarray, bits: int = 10) -> np.ndarray:
    """Vertex permutation sorting the base surface (V, 3) along a 3-D Morton (Z-order) curve."""
    lo, hi = base.min(axis=0), base.max(axis=0)
    q = ((base - lo) / np.maximum(hi - lo, 1e-12) * (2 ** bits - 1)).astype(np.int64)
    code = np.zeros(len(base), dtype=np.int64)
    for b in range(bits):
        for k in range(3):
            code |= ((q[:, k] >> b) & 1) << (3 * b + k)
    return np.argsort(code, kind="stable")


@dataclass(frozen=True)
class CandidateFeatures:
    """Features of n candidates: ``mesh`` (n, 3, V) scaled predicted offsets, ``act`` (n, A), ``extra`` (n, 2)."""

    mesh: np.ndarray
    act: np.ndarray
    extra: np.ndarray


def candidate_features(state: KsnnState, x_labelled: np.ndarray, x_cand: np.ndarray, order: np.ndarray,
                       scale: np.ndarray) -> CandidateFeatures:
    """Features of candidates ``x_cand`` under the predictor ``state`` trained on ``x_labelled``.

    ``scale`` (3,) are fixed per-axis offset scales (metres), so the CNN sees comparable magnitudes across states.
    """
    pred = predict(state, x_cand)[:, order, :] / scale  # (n, V, 3)
    mesh = np.ascontiguousarray(pred.transpose(0, 2, 1)).astype(np.float32)
    d = np.sqrt(((x_cand[:, None, :] - x_labelled[None, :, :]) ** 2).sum(-1)).min(axis=1)
    extra = np.stack([np.full(len(x_cand), np.log(len(x_labelled))), d / np.sqrt(x_cand.shape[1])], axis=1)
    return CandidateFeatures(mesh=mesh, act=np.asarray(x_cand, np.float32), extra=extra.astype(np.float32))


def concat(parts: list[CandidateFeatures]) -> CandidateFeatures:
    return CandidateFeatures(mesh=np.concatenate([p.mesh for p in parts]), act=np.concatenate([p.act for p in parts]),
                             extra=np.concatenate([p.extra for p in parts]))
