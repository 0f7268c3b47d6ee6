"""Active learning in the loop: choose which sampled poses to simulate next, batch by batch, and simulate them.

The dataset's planned poses are the candidates. A random initial batch is simulated first; then, until the budget
is spent, the AL predictor (``offline.active.learner``) is retrained on the converged poses simulated so far, the
selection rule (a learned GEN-LAL policy, or random for comparison) picks the next batch among the candidates not
yet simulated, and the engine simulates it. Every chosen batch is recorded in ``selection.json`` before it is
simulated, so a killed run first finishes the batch it was simulating and then goes on: rerunning the same command
resumes. Poses never chosen stay unsimulated (status "failed or missing" in the consolidated arrays, so training
uses only the simulated ones).

A dataset grown by selection is not an i.i.d. sample of the sampler: measure a predictor trained on it on a fresh
random dataset (``likeness offline evaluate --split all``), not on its own test split.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from models.atomic import write_bytes
from offline.active import learner
from offline.active.learner import LearnerConfig
from offline.active.policy import Policy
from offline.dataset.generate import generate_dataset
from offline.dataset.problem import ProblemSpec
from offline.dataset.store import PoseStore
from offline.engine import Engine

SELECTIONS = ("genlal", "random")


def _labelled(store: PoseStore, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices, normalized actuators and offsets of the converged poses simulated so far."""
    base = store.base()["vertices"]
    idx, xs, ys = [], [], []
    for i in sorted(store.done()):
        rec = store.read_pose(i)
        if rec.converged:
            idx.append(i)
            xs.append((rec.p - lo) / (hi - lo))
            ys.append(rec.surface - base)
    if not idx:
        return np.zeros(0, np.int64), np.zeros((0, len(lo))), np.zeros((0, len(base), 3))
    return np.asarray(idx), np.asarray(xs), np.asarray(ys, dtype=np.float64)


def grow_dataset(root: str | Path, spec: ProblemSpec, samples: np.ndarray, *, select: str, budget: int, batch: int,
                 init: int, policy: Policy | None, head: str, names: Sequence[str], units: Sequence[str],
                 lo: np.ndarray, hi: np.ndarray, engine: Engine, seed: int, sampling: dict[str, Any],
                 config: LearnerConfig | None = None, progress_stream: TextIO | None = sys.stderr,
                 log: Callable[[str], None] | None = None,
                 rest_pose: Sequence[float] | None = None) -> dict[str, Any]:
    """Simulate ``budget`` of the planned ``samples`` chosen by ``select``; resumable. Returns a summary.

    ``rest_pose`` is recorded in the manifest as by :func:`~offline.dataset.generate.generate_dataset`.
    """
    if select not in SELECTIONS:
        raise ValueError(f"unknown selection {select!r}; choose from {', '.join(SELECTIONS)}")
    if select == "genlal" and policy is None:
        raise ValueError("--select genlal needs a learned policy (--policy FILE, e.g. from likeness offline "
                         "al-benchmark: DIR/policy.npz)")
    if not 1 <= init <= budget <= len(samples) or batch < 1:
        raise ValueError(f"need 1 <= init ({init}) <= budget ({budget}) <= candidate poses ({len(samples)}) and "
                         f"batch >= 1 ({batch})")
    if policy is not None and policy.n_actuators != samples.shape[1]:
        raise ValueError(f"the policy was learned for {policy.n_actuators} actuators; this head has "
                         f"{samples.shape[1]}")
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    cfg = config or LearnerConfig()
    root = Path(root)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    # The budget is not part of the dataset's identity: rerunning with a larger one grows the same dataset further.
    sampling = {**sampling, "select": select, "batch": batch, "init": init}
    sel_path = root / "selection.json"

    def simulate(indices: Sequence[int]) -> dict[str, Any]:
        return generate_dataset(root, spec, samples, head=head, names=names, units=units, lo=lo, hi=hi,
                                engine=engine, seed=seed, sampling=sampling, progress_stream=progress_stream,
                                indices=indices, rest_pose=rest_pose)

    simulate([])  # creates the dataset folder (or checks it holds this run)
    store = PoseStore(root)
    doc = json.loads(sel_path.read_text()) if sel_path.exists() else {"select": select, "batches": []}
    batches: list[list[int]] = doc["batches"]
    if batches:
        simulate(batches[-1])  # finish the batch a killed run was simulating
    local_policy = None
    n_retrains = 0
    while sum(len(b) for b in batches) < budget:
        chosen_so_far = {i for b in batches for i in b}
        cand = np.asarray([i for i in range(len(samples)) if i not in chosen_so_far])
        size = min(budget - len(chosen_so_far), init if not batches else batch, len(cand))
        if not batches:
            pick = np.random.default_rng([seed, 0x100B]).choice(cand, size=size, replace=False)
        else:
            idx, x_lab, y_lab = _labelled(store, lo, hi)
            if len(idx) == 0:
                raise RuntimeError(f"{root}: no simulated pose converged; cannot train the predictor to select")
            state = learner.fit(x_lab, y_lab, cfg)
            n_retrains += 1
            x_cand = (samples[cand] - lo) / (hi - lo)
            if select == "genlal":
                if local_policy is None:
                    local_policy = policy.for_mesh(store.base()["vertices"], policy.scale)
                pick = cand[local_policy.select(state, x_lab, y_lab, x_cand, size, cfg)]
            else:
                pick = np.random.default_rng([seed, 0x100B, len(batches)]).choice(cand, size=size, replace=False)
            log(f"selection {select}: predictor retrained on {len(idx)} poses; batch {len(batches)} of {size} "
                f"poses chosen from {len(cand)} candidates")
        batches.append([int(i) for i in pick])
        write_bytes(sel_path, json.dumps({"select": select, "batches": batches}).encode())
        simulate(batches[-1])
    store.consolidate()
    idx, _, _ = _labelled(store, lo, hi)
    return {"root": str(root), "select": select, "candidates": len(samples), "budget": budget,
            "simulated": len(store.done()), "converged": len(idx), "batches": len(batches),
            "retrained_this_run": n_retrains}
