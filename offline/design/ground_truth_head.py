"""Ground truth on the head: recover a known skin thickness field and known actuations from noisy target surfaces.

On the sample head's skin, a random smooth thickness field (MLS over the design's samples, each height drawn in
h0 · [1 − v, 1 + v] and kept inside the head's thickness bounds) and a random actuation per target make the truth,
simulated on a finer discretization than the design uses (the skin extruded in ``truth_layers`` layers of tets, the
design in ``design_layers``; both share the outer surface, so a target is a set of outer-vertex positions). The
truth's outer surfaces get Gaussian noise of ``noise_m`` per coordinate. The design starts from the uniform skin
(the shipped geometry) and the head's neutral actuation, knowing only the noisy targets, and alternates actuation
per target (:func:`offline.design.actuation.optimize_targets`) and thickness
(:func:`offline.design.thickness.optimize_adjoint`) until the objective stops falling.

Figures (``report.json``): the thickness relative error over the free skin (every free column, not only the
samples: column height of the design against the truth's), the surface error before (uniform skin, actuation
optimized) and after against the noiseless truth, the actuation error as a fraction of each actuator's range, and
the goals (thickness within 10 % everywhere on the free skin, 3 % on average; surfaces within 3× the noise;
actuation within 1 % of range).
"""

from __future__ import annotations

import hashlib
import json
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from offline.fem.solve import SolverOptions

from .actuation import TargetResult, optimize_targets, simulate
from .face import FaceSkin, face_warp, load_face
from .layered import layered_skin_folder
from .thickness import Pose, ThicknessProblem, optimize_adjoint


@dataclass(frozen=True)
class HeadTruthSettings:
    """Size of the head ground-truth run. ``default()`` is the documented run; ``quick()`` the test-size one."""

    n_targets: int = 4
    n_samples: int = 16
    variation: float = 0.3  # true heights in h0 · [1 − v, 1 + v]
    actuation_spread: float = 0.25  # true actuation: neutral + U(−s, s) · range, projected into the limits
    noise_m: float = 5e-5
    truth_layers: int = 3
    design_layers: int = 2
    h_min: float = 0.003
    h_max: float = 0.012
    max_outer: int = 6
    thickness_iterations: int = 8
    actuation_iterations: int = 12
    tol: float = 1e-3  # stop when an outer iteration lowers the objective by less than this share
    width_factor: float = 1.2
    warp_weight: float = 1e-4

    @staticmethod
    def default() -> HeadTruthSettings:
        """The documented run: 4 targets, 16 samples, truth on 3 layers, design on 2."""
        return HeadTruthSettings()

    @staticmethod
    def quick() -> HeadTruthSettings:
        """Test size: 2 targets, 8 samples, 2 outer iterations."""
        return HeadTruthSettings(n_targets=2, n_samples=8, max_outer=2, thickness_iterations=4,
                                 actuation_iterations=6)


def column_heights(face: FaceSkin, X: np.ndarray) -> np.ndarray:
    """Height (m) of every column of a layered mesh at node positions X: its inner node's distance from its outer
    node (columns are numbered like the outer surface)."""
    S = len(face.outer)
    Xo = np.asarray(X)[np.asarray(face.outer)]
    return np.linalg.norm(np.asarray(X)[np.asarray(face.inner)] - Xo, axis=1) if len(face.inner) == S else \
        np.full(S, np.nan)


def _free_columns(face: FaceSkin) -> np.ndarray:
    """Columns (outer-vertex indices) whose inner node is not an attachment: where thickness is designed."""
    return np.flatnonzero(~np.isin(np.asarray(face.inner), face.locked))


def _thickness_problem(face: FaceSkin, warp, P: np.ndarray, targets: list[np.ndarray], s: HeadTruthSettings
                       ) -> ThicknessProblem:
    w = np.ones(len(face.outer))
    w[np.isin(face.outer, face.locked)] = 0.0
    return ThicknessProblem(warp, face.skin.material,
                            tuple(Pose(face.space.boundary(p), q) for p, q in zip(P, targets, strict=True)),
                            face.outer, s.h_min, s.h_max, warp_weight=s.warp_weight, region_weights=w,
                            solver=SolverOptions(backend=face.skin.spec.backend, tol_force=1e-8, max_iterations=60,
                                                 load_steps=1))


def make_truth(face_t: FaceSkin, warp_t, h0: np.ndarray, s: HeadTruthSettings, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """True heights, true actuations (T, A) and the truth's equilibrium states on the truth mesh."""
    from offline.fem.energy import min_jacobian

    space = face_t.space
    for _ in range(20):
        h_true = np.clip(h0 * (1 + rng.uniform(-s.variation, s.variation, h0.shape)), s.h_min + 2e-4,
                         s.h_max - 2e-4)
        if min_jacobian(warp_t.mesh, warp_t.rest_positions(h_true)) > 0.05:
            break
    else:
        raise RuntimeError("no random thickness field kept the truth mesh unfolded in 20 draws")
    problem = face_t.actuation_problem(warp_t.rest_mesh(h_true))
    P, xs = [], []
    prev = None
    while len(P) < s.n_targets:
        p = space.neutral + rng.uniform(-s.actuation_spread, s.actuation_spread, space.neutral.shape) * (
            space.hi - space.lo)
        p = space.expand(space.project(space.reduce(p)))
        x = simulate(problem, p, prev)
        if x is None:
            continue
        P.append(p)
        xs.append(x)
        prev = x
    return h_true, np.array(P), xs


def identifiability(problem: ThicknessProblem, h: np.ndarray, xs: list[np.ndarray]) -> dict:
    """How well the targets determine the sample heights: the standard deviation of each height per unit of
    surface noise (m per m, from the Fisher information Σ J_kᵀ J_k of the matched outer coordinates with the
    actuation known, so an optimistic bound), and the noise (m per coordinate) at which every height's standard
    deviation is 10 % of it (``noise_for_10pct_max_m``) or their RMS is 3 % (``noise_for_3pct_rms_m``)."""
    from .thickness import _match_scale, sensitivities, solve_poses

    state = solve_poses(problem, h, xs)
    if state is None:
        return {}
    _, Js = sensitivities(problem, state)
    fisher = sum(J.T @ J for J in Js) / _match_scale(problem)  # J's rows carry √(scale · w), w = 1 where matched
    cov_unit = np.linalg.pinv(fisher)
    std = np.sqrt(np.clip(np.diag(cov_unit), 0.0, None))
    rel = std / h
    sv = np.linalg.svd(fisher, compute_uv=False)
    return {"height_std_per_unit_noise": std.tolist(), "noise_for_10pct_max_m": float(0.10 / rel.max()),
            "noise_for_3pct_rms_m": float(0.03 / np.sqrt(np.mean(rel ** 2))),
            "fisher_condition": float(sv[0] / max(sv[-1], 1e-300))}


def _surface_errors(face: FaceSkin, xs: list[np.ndarray], truth: list[np.ndarray]) -> dict[str, float]:
    e = np.concatenate([np.linalg.norm(np.asarray(x)[face.outer] - q, axis=1) for x, q in zip(xs, truth,
                                                                                               strict=True)])
    return {"surface_error_mean_m": float(e.mean()), "surface_error_max_m": float(e.max())}


def design(face: FaceSkin, warp, h0: np.ndarray, targets: list[np.ndarray], truth: list[np.ndarray],
           s: HeadTruthSettings, progress: Callable[[str], None]) -> tuple[np.ndarray, list[TargetResult], list[dict]]:
    """Actuation on the uniform skin from neutral, then thickness and actuation alternated until an outer
    iteration gains less than ``s.tol``; returns the heights, the per-target results and the log (its first
    entry, the uniform skin's, carries the actuation ``P`` found there)."""
    h = np.clip(h0, s.h_min + 1e-5, s.h_max - 1e-5)
    act = face.actuation_problem()
    res = optimize_targets(act, targets, max_iterations=s.actuation_iterations)
    total = float(sum(r.match for r in res))
    first = _surface_errors(face, [r.x for r in res], truth)
    log = [{"stage": "actuation", "objective": total, **first, "P": np.array([r.p for r in res]).tolist()}]
    progress(f"[ground truth] uniform skin, actuation optimized: surface error mean "
             f"{first['surface_error_mean_m'] * 1e3:.3f} mm")
    for outer in range(1, s.max_outer + 1):
        tp = _thickness_problem(face, warp, np.array([r.p for r in res]), targets, s)
        tres = optimize_adjoint(tp, h, max_iterations=s.thickness_iterations, warm=[r.x for r in res],
                                tol_gain=1e-4)
        prev = [TargetResult(r.p, x, 0.0, 0.0, 0, True, 0, [], 0.0) for r, x in zip(res, tres.xs, strict=True)]
        new = optimize_targets(act.with_mesh(warp.rest_mesh(tres.h)), targets, previous=prev,
                               max_iterations=s.actuation_iterations)
        value = float(sum(r.match for r in new))
        err = _surface_errors(face, [r.x for r in new], truth)
        log.append({"stage": "outer", "outer": outer, "objective": value, "thickness_iterations": tres.iterations,
                    **err})
        progress(f"[ground truth] outer {outer}: objective {total:.4g} -> {value:.4g}, surface error mean "
                 f"{err['surface_error_mean_m'] * 1e3:.3f} mm")
        if value <= total:
            h, res = tres.h, new
        if total - value <= s.tol * total:
            break
        total = min(total, value)
    return h, res, log


def run_head_ground_truth(config: str | Path, out: str | Path, seed: int = 0,
                          settings: HeadTruthSettings = HeadTruthSettings(),
                          progress: Callable[[str], None] = lambda line: None) -> dict:
    """Run the head ground-truth test and write ``out/report.json`` and ``out/thickness_recovery.png``."""
    s = settings
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    src = Path(config).resolve().parent / "skin"
    rng = np.random.default_rng(seed)
    layered_skin_folder(src, out / "truth_mesh", layers=s.truth_layers)
    layered_skin_folder(src, out / "design_mesh", layers=s.design_layers)
    face_t = load_face(config, out / "truth_mesh")
    face_d = load_face(config, out / "design_mesh")
    warp_t, h0 = face_warp(face_t, n_samples=s.n_samples, width_factor=s.width_factor)
    warp_d, h0_d = face_warp(face_d, n_samples=s.n_samples, width_factor=s.width_factor)
    if not np.allclose(warp_t.samples_uv, warp_d.samples_uv):
        raise RuntimeError("truth and design meshes placed their thickness samples differently")
    progress(f"[ground truth] truth {face_t.mesh.n_nodes} nodes / design {face_d.mesh.n_nodes} nodes; "
             f"{s.n_samples} samples, {s.n_targets} targets")
    h_true, P_true, xs_true = make_truth(face_t, warp_t, h0, s, rng)
    truth_surf = [np.asarray(x)[face_t.outer] for x in xs_true]
    targets = [q + rng.normal(scale=s.noise_m, size=q.shape) for q in truth_surf]
    progress(f"[ground truth] truth made ({time.perf_counter() - t0:.0f} s); designing from the uniform skin")
    h, res, log = design(face_d, warp_d, h0_d, targets, truth_surf, s,
                         lambda line: progress(f"{line} ({time.perf_counter() - t0:.0f} s)"))
    before = {k: log[0][k] for k in ("surface_error_mean_m", "surface_error_max_m")}
    P_before = np.asarray(log[0].pop("P"))
    after = _surface_errors(face_d, [r.x for r in res], truth_surf)
    P = np.array([r.p for r in res])
    ident = identifiability(_thickness_problem(face_d, warp_d, P, targets, s), h, [r.x for r in res])
    free = _free_columns(face_d)
    ht = column_heights(face_t, warp_t.rest_positions(h_true))
    hd = column_heights(face_d, warp_d.rest_positions(h))
    h_start = column_heights(face_d, np.asarray(face_d.mesh.nodes))
    rel = np.abs(hd - ht)[free] / ht[free]
    rel_start = np.abs(h_start - ht)[free] / ht[free]
    span = face_d.space.hi - face_d.space.lo
    act_err = np.abs(P - P_true) / span
    report = {
        "head": str(config), "seed": seed, "settings": asdict(s), "noise_m": s.noise_m,
        "truth": {"element_order": face_t.mesh.order, "n_nodes": face_t.mesh.n_nodes, "n_tets": face_t.mesh.n_tets,
                  "layers": s.truth_layers},
        "design": {"element_order": face_d.mesh.order, "n_nodes": face_d.mesh.n_nodes,
                   "n_tets": face_d.mesh.n_tets, "layers": s.design_layers},
        "free_columns": int(free.size),
        "thickness_rel_error_max": float(rel.max()), "thickness_rel_error_mean": float(rel.mean()),
        "thickness_rel_error_p90": float(np.percentile(rel, 90)),
        "thickness_rel_error_start_mean": float(rel_start.mean()),
        "thickness_rel_error_start_max": float(rel_start.max()),
        "sample_heights": {"true": h_true.tolist(), "recovered": h.tolist(), "start": h0_d.tolist()},
        "before": before, "after": after,
        "after_against_noisy_targets": _surface_errors(face_d, [r.x for r in res], targets),
        "actuation_error_max": float(act_err.max()), "actuation_error_mean": float(act_err.mean()),
        "actuation_error_start_max": float((np.abs(P_before - P_true) / span).max()),
        "identifiability": ident,
        "goals": {"thickness_rel_error_max": 0.10, "thickness_rel_error_mean": 0.03,
                  "surface_error_mean_m": 3 * s.noise_m, "actuation_error_max": 0.01},
        "log": log, "seconds": time.perf_counter() - t0,
        "inputs_sha256": {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
                          for p in (Path(config), src / "skin.vtu", src / "face_units.npz")},
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
    }
    g = report["goals"]
    report["goals_met"] = {"thickness_rel_error_max": report["thickness_rel_error_max"] <= g["thickness_rel_error_max"],
                           "thickness_rel_error_mean":
                               report["thickness_rel_error_mean"] <= g["thickness_rel_error_mean"],
                           "surface_error_mean_m": after["surface_error_mean_m"] <= g["surface_error_mean_m"],
                           "actuation_error_max": report["actuation_error_max"] <= g["actuation_error_max"]}
    _picture(out / "thickness_recovery.png", face_d, ht, hd, free)
    from models.atomic import write_text

    write_text(out / "report.json", json.dumps(report, indent=1, default=float) + "\n")
    return report


def _picture(path: Path, face: FaceSkin, ht: np.ndarray, hd: np.ndarray, free: np.ndarray) -> None:
    """True thickness, recovered thickness and their relative error on the free columns, front view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .face import surface_frame

    X = np.asarray(face.mesh.nodes)[face.outer]
    c, axes = surface_frame(X)
    uv = (X - c) @ axes[:2].T * 1e3
    fig, axs = plt.subplots(1, 3, figsize=(13, 4.4), constrained_layout=True)
    lo, hi = float(min(ht[free].min(), hd[free].min())) * 1e3, float(max(ht[free].max(), hd[free].max())) * 1e3
    rel = (hd - ht)[free] / ht[free] * 100
    lim = max(float(np.abs(rel).max()), 1.0)
    for ax, vals, title, kw in ((axs[0], ht[free] * 1e3, "true thickness (mm)", {"vmin": lo, "vmax": hi}),
                                (axs[1], hd[free] * 1e3, "recovered thickness (mm)", {"vmin": lo, "vmax": hi}),
                                (axs[2], rel, "relative error (%)", {"vmin": -lim, "vmax": lim,
                                                                     "cmap": "RdBu_r"})):
        ax.scatter(uv[:, 0], uv[:, 1], s=3, c="0.85")
        sc = ax.scatter(uv[free, 0], uv[free, 1], s=8, c=vals, **kw)
        ax.set_title(title, fontsize=9)
        ax.set_aspect("equal")
        ax.set_axis_off()
        fig.colorbar(sc, ax=ax, shrink=0.8)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def quick_settings(**changes) -> HeadTruthSettings:
    """The test-size settings with ``changes``."""
    return replace(HeadTruthSettings.quick(), **changes)
