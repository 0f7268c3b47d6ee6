"""Batch selection rules compared in the benchmark: GEN-LAL and the baselines, behind one signature.

Every rule gets a :class:`SelectionContext` (the pool's normalized actuators, the labelled and candidate pool
rows, the predictor trained on the labelled rows, the batch size, a seeded generator) and returns the chosen
candidate rows. Only ``greedy`` reads labels of unlabelled poses (``ctx.oracle_y``): it is the fully informed
upper bound, not a usable method.

- ``random``: a uniform batch of candidates.
- ``greedy``: fully informed, batch-aware look-ahead. A family of 12 whole candidate batches
  (``offline.active.batches.batch_family``: the farthest-point batch, and batches mixing the current predictor's
  true error on each candidate with distance at several weights), each added to the labelled set and the predictor
  retrained **from scratch with the benchmark's own schedule and seed**; the batch whose retrained predictor has
  the lowest mean error over the whole pool (every pool label known) wins. It never reads the test set.
- ``space_filling``: farthest-point (max-min distance) batch in normalized actuator space.
- ``committee``: variance of a committee of predictors (different seeds, bootstrap resamples of the labelled set)
  summed over the surface; the top batch.
- ``lcmd`` / ``maxdist``: ``bmdal-reg``'s LCMD and MaxDist in TP mode on the predictor's gradient features (base
  kernel ``grad``, random projection to 512 features), called through its API. bmdal-reg works on scalar-output
  networks, so the KSNN is given to it as the network whose output is the projection of the offsets on their first
  principal direction over the labelled poses: the same hidden layer (the three axes' hidden units side by side)
  with that projection folded into the output layer.
- ``genlal``: the learned policy (``offline.active.policy``), Algorithm 2.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from offline.active import learner
from offline.active.learner import KsnnState, LearnerConfig


@dataclass
class SelectionContext:
    """What a selection rule may look at for one batch (positions index the pool arrays)."""

    x: np.ndarray  # (N, A) normalized actuators of the whole pool
    labelled: np.ndarray  # pool rows already labelled
    candidates: np.ndarray  # pool rows still selectable
    y_labelled: np.ndarray  # (n_labelled, V, 3) labels of the labelled rows
    state: KsnnState  # predictor trained on the labelled rows
    batch: int
    rng: np.random.Generator
    config: LearnerConfig
    oracle_y: np.ndarray | None = None  # (N, V, 3) every pool label: only the fully informed oracle reads it


Selector = Callable[[SelectionContext], np.ndarray]


def select_random(ctx: SelectionContext) -> np.ndarray:
    return ctx.rng.choice(ctx.candidates, size=ctx.batch, replace=False)


def select_greedy(ctx: SelectionContext, family: int = 12) -> np.ndarray:
    if ctx.oracle_y is None:
        raise ValueError("the greedy fully informed oracle needs every pool label")
    from offline.active.batches import batch_family, family_seed

    y_all = ctx.oracle_y
    cand, lab = ctx.candidates, ctx.labelled
    err = np.linalg.norm(learner.predict(ctx.state, ctx.x[cand]) - y_all[cand], axis=2).mean(axis=1)
    rng = family_seed(len(lab), int(ctx.rng.integers(2 ** 31)))
    batches = batch_family(err[:, None], ctx.x[lab], ctx.x[cand], ctx.batch, family, rng)
    best, chosen = np.inf, batches[0]
    for b in batches:
        idx = np.concatenate([lab, cand[b]])
        judged = learner.mean_error(learner.fit(ctx.x[idx], y_all[idx], ctx.config), ctx.x, y_all)
        if judged < best:
            best, chosen = judged, b
    return cand[chosen]


def select_space_filling(ctx: SelectionContext) -> np.ndarray:
    x = ctx.x
    d = np.sqrt(((x[ctx.candidates][:, None, :] - x[ctx.labelled][None, :, :]) ** 2).sum(-1)).min(axis=1)
    chosen: list[int] = []
    for _ in range(ctx.batch):
        j = int(np.argmax(d))
        chosen.append(int(ctx.candidates[j]))
        d = np.minimum(d, np.sqrt(((x[ctx.candidates] - x[ctx.candidates[j]]) ** 2).sum(-1)))
        d[j] = -1.0
    return np.asarray(chosen)


def select_committee(ctx: SelectionContext, members: int = 4) -> np.ndarray:
    lab = ctx.labelled
    preds = []
    for m in range(members):
        boot = ctx.rng.choice(len(lab), size=len(lab), replace=True)
        boot = np.unique(np.concatenate([boot, ctx.rng.choice(len(lab), size=min(2, len(lab)), replace=False)]))
        st = learner.fit(ctx.x[lab][boot], ctx.y_labelled[boot], ctx.config, seed=ctx.config.seed + 1000 + m)
        preds.append(learner.predict(st, ctx.x[ctx.candidates]))
    var = np.var(np.stack(preds), axis=0).sum(axis=2).mean(axis=1)  # (n_cand,)
    return ctx.candidates[np.argsort(-var, kind="stable")[:ctx.batch]]


def scalar_network(state: KsnnState, y_labelled: np.ndarray):
    """The KSNN as a torch network with one output: the offsets projected on their first principal direction."""
    import torch
    from torch import nn

    y = np.asarray(y_labelled, np.float64) / state.scale  # scaled like the network's outputs
    yc = (y - y.mean(axis=0)).reshape(len(y), -1)
    if len(y) > 1 and np.abs(yc).max() > 0:
        u = np.linalg.svd(yc, full_matrices=False)[2][0].reshape(-1, 3)  # (V, 3)
    else:
        u = np.ones((y.shape[1], 3)) / np.sqrt(3 * y.shape[1])
    W1 = state.W1.numpy()  # (3, A, H)
    b1 = state.b1.numpy()[:, 0, :]  # (3, H)
    W2 = state.W2.numpy()  # (3, H + 1, V)
    n_act, hidden = W1.shape[1], W1.shape[2]
    w_out = np.concatenate([W2[k, :hidden, :] @ u[:, k] for k in range(3)])  # (3H,)
    b_out = sum(float(W2[k, hidden, :] @ u[:, k]) for k in range(3))
    net = nn.Sequential(nn.Linear(n_act, 3 * hidden), nn.Tanh(), nn.Linear(3 * hidden, 1))
    with torch.no_grad():
        net[0].weight.copy_(torch.from_numpy(np.concatenate([W1[k].T for k in range(3)])))
        net[0].bias.copy_(torch.from_numpy(b1.reshape(-1)))
        net[2].weight.copy_(torch.from_numpy(w_out[None, :]))
        net[2].bias.fill_(b_out)
    return net.float()


def _numpy2_alias() -> None:
    """bmdal-reg 3.0.2 writes ``np.Inf``, an alias NumPy 2 removed; restore it (the same constant) before calling."""
    if "Inf" not in np.__dict__:
        np.Inf = np.inf  # type: ignore[attr-defined]


def _bmdal(ctx: SelectionContext, method: str) -> np.ndarray:
    import torch
    from bmdal_reg.bmdal.algorithms import select_batch
    from bmdal_reg.bmdal.feature_data import TensorFeatureData

    _numpy2_alias()
    torch.manual_seed(int(ctx.rng.integers(2 ** 31)))
    net = scalar_network(ctx.state, ctx.y_labelled)
    data = {"train": TensorFeatureData(torch.from_numpy(ctx.x[ctx.labelled].astype(np.float32))),
            "pool": TensorFeatureData(torch.from_numpy(ctx.x[ctx.candidates].astype(np.float32)))}
    idx, _ = select_batch(batch_size=ctx.batch, models=[net], data=data, y_train=None, base_kernel="grad",
                          kernel_transforms=[("rp", [512])], selection_method=method, sel_with_train=True)
    return ctx.candidates[idx.numpy()]


def select_lcmd(ctx: SelectionContext) -> np.ndarray:
    return _bmdal(ctx, "lcmd")


def select_maxdist(ctx: SelectionContext) -> np.ndarray:
    return _bmdal(ctx, "maxdist")


class GenlalSelector:
    """Algorithm 2 with a learned :class:`~offline.active.policy.Policy` (an object, not a closure, so a benchmark
    can hand it to its worker processes)."""

    def __init__(self, policy) -> None:
        self.policy = policy

    def __call__(self, ctx: SelectionContext) -> np.ndarray:
        pos = self.policy.select(ctx.state, ctx.x[ctx.labelled], ctx.y_labelled, ctx.x[ctx.candidates], ctx.batch,
                                 ctx.config)
        return ctx.candidates[pos]


def genlal_selector(policy) -> Selector:
    """Algorithm 2 with a learned :class:`~offline.active.policy.Policy`."""
    return GenlalSelector(policy)


BASELINES: dict[str, Selector] = {
    "random": select_random,
    "greedy": select_greedy,
    "space_filling": select_space_filling,
    "committee": select_committee,
    "lcmd": select_lcmd,
    "maxdist": select_maxdist,
}
METHODS: tuple[str, ...] = ("random", "greedy", "space_filling", "committee", "lcmd", "maxdist", "genlal")
