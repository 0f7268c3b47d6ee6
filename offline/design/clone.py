"""Face cloning of a head: actuation alone on the uniform skin, then thickness and actuation alternated.

Stages (each outer iteration is checkpointed to ``DIR/checkpoint.npz``, so a killed run resumes where it stopped):

1. **predictor**: the runtime's predictor-based inverse (``models.ksnn_solve``) per target, simulated with the FEM:
   the runtime's answer, and the start of the FEM-exact solve.
2. **actuation** on the skin as loaded (uniform thickness): :func:`offline.design.actuation.optimize_targets`.
   Its errors are the report's "before".
3. **outer iterations**: thickness (:func:`offline.design.thickness.optimize_adjoint`, Gauss-Newton, MLS samples
   placed denser where the target poses strain the skin most) with the actuation fixed, then the actuation again
   on the new rest shape. The thickness step matches the outer surface by region, weighted: vertices near the
   links and the skull (``link_weight``) and the free skin between them (``free_weight``); outer vertices that
   are attachment nodes themselves get weight 0 (no thickness moves them). It iterates until its Gauss-Newton
   model predicts less than ``tol_gain`` of its matching term from a further step (the part thickness can change
   is spent) or ``thickness_iterations``. The outer loop stops when a thickness step finds nothing to gain
   (predicted gain below ``tol_gain`` at its start), when an iteration does not improve the total objective by
   more than ``tol`` (relative; an iteration that ends worse is discarded) or after ``max_outer``. Each outer
   log entry holds the reachability split of the thickness step's start (per target, the share of its matching
   term that no thickness change can remove, to first order). The final errors are the report's "after".

With ``strain_constraint`` (the default) every actuation solve keeps its pose inside the head's validated strain
range, measured with the runtime guard's measure (:mod:`offline.design.strain_constraint`); the thickness step does
not see the constraint, the actuation step after it restores it on the new rest shape (the outer surface the measure
lives on is fixed by the design), so every pose the run returns has been checked with the exact measure.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from offline.fem.solve import SolverOptions

from .actuation import TargetResult, optimize_targets, simulate
from .face import FaceSkin, face_warp
from .targets import target_surface, unit_weights
from .thickness import Pose, ThicknessProblem, optimize_adjoint
from .warp import strain_density

CHECKPOINT = "checkpoint.npz"


@dataclass(frozen=True)
class CloneSettings:
    """Optimization settings (SI)."""

    n_samples: int = 40
    width_factor: float = 1.2
    h_min: float = 0.003
    h_max: float = 0.012
    max_outer: int = 4
    actuation_iterations: int = 12
    thickness_iterations: int = 8
    tol: float = 2e-3
    tol_gain: float = 1e-3  # thickness step: stop when its model predicts less than this share of its match
    link_weight: float = 1.0  # thickness matching weight of outer vertices near a link or the skull
    free_weight: float = 1.0  # ... of the free skin between attachments
    warp_weight: float = 1e-3
    goal_mean_m: float = 1.35e-3
    goal_max_m: float = 4e-3
    tol_force: float = 1e-8
    strain_constraint: bool = True  # every pose inside the head's validated strain range (the guard's measure)
    strain_margin: float = 0.01  # the constraint's hinge sits this far (strain) inside the range
    element_order: int = 1  # of the design mesh (the face is loaded at this order; recorded for the checkpoint)
    layers: int = 0  # elements through the thickness of a layered design mesh (0: the skin mesh as it is)


Progress = Callable[[str], None]


class _Clock:
    """Elapsed time and a linear ETA over a known number of work units."""

    def __init__(self, total: int) -> None:
        self.t0 = time.perf_counter()
        self.total = max(total, 1)
        self.done = 0

    def eta(self) -> str:
        el = time.perf_counter() - self.t0
        if self.done == 0:
            return f"elapsed {el:.0f}s  ETA ?"
        left = el / self.done * max(self.total - self.done, 0)
        return f"elapsed {el:.0f}s  ETA {left / 60:.1f} min"


def vertex_errors(x_outer: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Per-vertex distance (m) between corresponding simulated and target outer-surface vertices."""
    return np.linalg.norm(np.asarray(x_outer) - np.asarray(target), axis=1)


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance (K,) from points p (K, 3) to triangles tri (K, 3, 3) (closest point by region, Ericson's method)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        q = a + ab * v_in[:, None] + ac * w_in[:, None]  # interior
        t_ab = np.clip(d1 / (d1 - d3), 0, 1)
        t_ac = np.clip(d2 / (d2 - d6), 0, 1)
        t_bc = np.clip((d4 - d3) / ((d4 - d3) + (d5 - d6)), 0, 1)
    edge_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    edge_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    edge_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    q = np.where(edge_bc[:, None], b + (c - b) * t_bc[:, None], q)
    q = np.where(edge_ac[:, None], a + ac * t_ac[:, None], q)
    q = np.where(edge_ab[:, None], a + ab * t_ab[:, None], q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    return np.linalg.norm(p - q, axis=1)


def surface_distances(x_outer: np.ndarray, target: np.ndarray, faces: np.ndarray, candidates: int = 24
                      ) -> np.ndarray:
    """Per-vertex distance (m) from each simulated outer vertex to the closest point of the target surface (the
    exact point-triangle distance to the ``candidates`` triangles whose centroids lie nearest)."""
    from scipy.spatial import cKDTree

    x = np.asarray(x_outer, dtype=np.float64)
    tri = np.asarray(target, dtype=np.float64)[faces]
    k = min(candidates, len(faces))
    _, idx = cKDTree(tri.mean(axis=1)).query(x, k=k)
    idx = idx.reshape(len(x), k)
    d = point_triangle_distance(np.repeat(x, k, axis=0), tri[idx.ravel()]).reshape(len(x), k)
    return d.min(axis=1)


def predictor_inverse(face: FaceSkin, names: tuple[str, ...], weights: list[np.ndarray]) -> list[np.ndarray] | None:
    """The runtime's inverse (hidden-space Gauss-Newton on the head's KSNN predictor) per target, or None when the
    head has no predictor or it carries no face units."""
    from models.ksnn_solve import KsnnInverse
    from models.predictor import SkinPredictor

    head = face.skin.head
    path = head.path("predictor")
    if path is None or not Path(path).is_file():
        return None
    sp = SkinPredictor(path)
    if sp.face_unit_offsets is None or tuple(sp.face_unit_names) != tuple(names):
        return None
    lo = np.maximum([a.min for a in head.actuators], sp.lo)
    hi = np.minimum([a.max for a in head.actuators], sp.hi)
    inv = KsnnInverse(sp.weights, sp.face_unit_offsets, smoothness=0.0, lo=lo, hi=hi)
    neutral = np.clip(head.neutral_pose, lo, hi)
    return [inv.solve(w, p0=neutral, max_iterations=50, tol=1e-12).p for w in weights]


class CloneRun:
    """One face-cloning run: targets, settings, output folder, checkpoint and progress lines."""

    def __init__(self, face: FaceSkin, targets: Mapping[str, Mapping[str, float]], out_dir: str | Path,
                 settings: CloneSettings = CloneSettings(), progress: Progress = print) -> None:
        self.face = face
        self.settings = settings
        self.out = Path(out_dir)
        self.say = progress
        self.target_names = tuple(targets)
        self.target_weights = {n: dict(w) for n, w in targets.items()}
        self.unit_names, offsets = face.skin.face_units()
        if offsets is None:
            raise ValueError(f"{face.mesh_dir}: the skin carries no face units; targets cannot be built")
        self.rest_outer = np.asarray(face.mesh.nodes)[face.outer]
        self.targets = [target_surface(self.rest_outer, offsets, self.unit_names, w) for w in targets.values()]
        self.weights = [unit_weights(w, self.unit_names) for w in targets.values()]
        self.problem = face.actuation_problem(tol_force=settings.tol_force)
        if settings.strain_constraint:
            from dataclasses import replace

            from .strain_constraint import face_strain_constraint

            self.problem = replace(self.problem, strain=face_strain_constraint(face, margin=settings.strain_margin))

    def region_weights(self) -> np.ndarray:
        """Thickness matching weight per outer vertex: ``link_weight`` near links and skull, ``free_weight`` on the
        free skin, 0 on outer vertices that are attachment nodes (their position is the link's, not the skin's)."""
        from offline.dataset.regions import FREE

        names, labels = self.face.skin.surface_regions()
        free = labels == names.index(FREE) if FREE in names else np.zeros(labels.size, dtype=bool)
        w = np.where(free, self.settings.free_weight, self.settings.link_weight)
        w[np.isin(self.face.outer, self.face.locked)] = 0.0
        return w

    def thickness_problem(self, warp, P: np.ndarray) -> ThicknessProblem:
        """The thickness step's problem: the targets posed at actuations ``P``, matched by region weights."""
        s, face = self.settings, self.face
        return ThicknessProblem(warp, face.skin.material,
                                tuple(Pose(face.space.boundary(p), q) for p, q in zip(P, self.targets, strict=True)),
                                face.outer, s.h_min, s.h_max, warp_weight=s.warp_weight,
                                region_weights=self.region_weights(),
                                solver=SolverOptions(backend=face.skin.spec.backend, tol_force=s.tol_force,
                                                     max_iterations=60, load_steps=1))

    # ------------------------------------------------------------------ checkpoint
    def _save(self, state: dict) -> None:
        from models.atomic import atomic_path

        self.out.mkdir(parents=True, exist_ok=True)
        arrays = {k: np.asarray(v) for k, v in state.items() if isinstance(v, np.ndarray)}
        meta = {k: v for k, v in state.items() if not isinstance(v, np.ndarray)}
        with atomic_path(self.out / CHECKPOINT, suffix=".npz") as tmp:
            np.savez(tmp, meta=np.array(json.dumps(meta, default=float)), **arrays)

    def _load(self) -> dict | None:
        path = self.out / CHECKPOINT
        if not path.exists():
            return None
        with np.load(path) as z:
            state = dict(json.loads(str(z["meta"])))
            for k in z.files:
                if k != "meta":
                    state[k] = np.asarray(z[k])
        if state.get("targets") != list(self.target_names) or state.get("settings") != _jsonable(self.settings):
            self.say(f"[clone] {path}: made for other targets or settings; starting over")
            return None
        return state

    # ------------------------------------------------------------------ stages
    def _errors(self, xs: list[np.ndarray]) -> list[dict]:
        out = []
        for x, q in zip(xs, self.targets, strict=True):
            ev = vertex_errors(x[self.face.outer], q)
            sd = surface_distances(x[self.face.outer], q, self.face.faces)
            out.append({"vertex_mean_m": float(ev.mean()), "vertex_max_m": float(ev.max()),
                        "surface_mean_m": float(sd.mean()), "surface_max_m": float(sd.max())})
        return out

    def _actuation(self, mesh, previous: list[TargetResult] | None, starts, label: str, clock: _Clock
                   ) -> list[TargetResult]:
        problem = self.problem.with_mesh(mesh)
        names = self.target_names

        def progress(k: int, entry: dict) -> None:
            self.say(f"[clone] {label} target {k + 1}/{len(names)} {names[k]} it {entry['iteration']} "
                     f"objective {entry['objective']:.4g}  {clock.eta()}")

        results = []
        for k in range(len(names)):
            res = optimize_targets(problem, [self.targets[k]], starts=[starts[k]] if starts is not None else None,
                                   previous=[previous[k]] if previous is not None else None,
                                   max_iterations=self.settings.actuation_iterations, tol_value=1e-3,
                                   progress=lambda i, e, k=k: progress(k, e))[0]
            results.append(res)
            err = vertex_errors(res.x[self.face.outer], self.targets[k])
            clock.done += 1
            strain = ""
            if res.strain is not None:
                strain = (f", strain {res.strain[0]:+.1%} / {res.strain[1]:+.1%} "
                          f"({'inside' if res.strain_inside else 'OUTSIDE'} the range, weight {res.strain_weight:.0e})")
            self.say(f"[clone] {label} target {k + 1}/{len(names)} {names[k]} done: {res.iterations} it, "
                     f"objective {res.value:.4g}, error mean {err.mean() * 1e3:.2f} max {err.max() * 1e3:.2f} mm"
                     f"{strain} (start: {res.start})  {clock.eta()}")
        return results

    def run(self, resume: bool = True) -> dict:
        """Run (or resume) every stage; returns the in-memory results used by the report."""
        s = self.settings
        face = self.face
        state = self._load() if resume else None
        n_t = len(self.targets)
        clock = _Clock(n_t * (2 + 2 * s.max_outer))
        t_start = time.perf_counter()
        base = {"targets": list(self.target_names), "settings": _jsonable(s)}
        # 1. the runtime's predictor inverse, simulated
        if state is None:
            self.say(f"[clone] predictor inverse on {n_t} targets (FEM check of each)  {clock.eta()}")
            p_pred = predictor_inverse(face, self.unit_names, self.weights)
            xs_pred = []
            if p_pred is not None:
                x_prev = None
                for p in p_pred:
                    x = simulate(self.problem, p, x_prev)
                    xs_pred.append(x if x is not None else np.full((face.mesh.n_nodes, 3), np.nan))
                    x_prev = x if x is not None else x_prev
            clock.done += n_t
            state = {**base, "stage": "predictor", "seconds": time.perf_counter() - t_start,
                     "P_pred": np.asarray(p_pred) if p_pred is not None else np.zeros((0,)),
                     "X_pred": np.asarray(xs_pred) if xs_pred else np.zeros((0,))}
            self._save(state)
        else:
            self.say(f"[clone] resuming from {self.out / CHECKPOINT} (stage {state['stage']}, "
                     f"outer iteration {state.get('outer', 0)})")
        p_pred = state["P_pred"] if np.asarray(state["P_pred"]).size else None
        # 2. actuation alone on the uniform skin
        if state["stage"] == "predictor":
            res = self._actuation(face.mesh, None, list(p_pred) if p_pred is not None else None,
                                  "actuation (uniform skin)", clock)
            state.update(stage="actuation", outer=0, P_before=np.array([r.p for r in res]),
                         X_before=np.array([r.x for r in res]), W_before=np.array([r.strain_weight for r in res]),
                         seconds=state["seconds"] + clock_elapsed(t_start),
                         log=[{"stage": "actuation", "objective": float(sum(r.match for r in res))}])
            self._save(state)
        # 3. thickness + actuation
        warp, h0 = face_warp(face, n_samples=s.n_samples, width_factor=s.width_factor,
                             density=strain_density(face.mesh, list(state["X_before"])))
        h = np.asarray(state.get("h", h0), dtype=np.float64)
        P = np.asarray(state.get("P", state["P_before"]))
        X = np.asarray(state.get("X", state["X_before"]))
        W = np.asarray(state.get("W", state.get("W_before", np.zeros(n_t))), dtype=np.float64)
        total = float(state["log"][-1]["objective"])
        outer = int(state.get("outer", 0))
        clock.done = n_t * (2 + 2 * outer)
        while state["stage"] != "done" and outer < s.max_outer:
            outer += 1
            t_it = time.perf_counter()
            tp = self.thickness_problem(warp, P)
            self.say(f"[clone] outer {outer}: thickness ({warp.n_samples} samples, {s.thickness_iterations} "
                     f"Gauss-Newton iterations at most)  {clock.eta()}")
            tres = optimize_adjoint(tp, np.clip(h, s.h_min + 1e-5, s.h_max - 1e-5), method="gauss-newton",
                                    max_iterations=s.thickness_iterations, warm=list(X), verbose=False,
                                    tol_gain=s.tol_gain)
            clock.done += n_t
            t_obj = float(tres.log[-1]["match"])
            split = _split(tres.log[0])
            self.say(f"[clone] outer {outer}: thickness step {tres.iterations} it; at its start "
                     f"{split['reachable_share']:.1%} of its matching term was within thickness's reach "
                     f"(first order)  {clock.eta()}")
            if tres.iterations <= 1 and tres.converged and "next_predicted_gain" in tres.log[0]:
                self.say(f"[clone] outer {outer}: the thickness step predicts less than {s.tol_gain:.1%} gain: "
                         "thickness has nothing left to change; stopping")
                state["log"] = [*state["log"], {"stage": "outer", "outer": outer, "objective": total,
                                                "thickness_reachability": split, "converged": "thickness"}]
                state.update(stage="done", outer=outer)
                self._save(state)
                break
            self.say(f"[clone] outer {outer}: thickness objective {total:.4g} -> {t_obj:.4g} "
                     f"(heights {tres.h.min() * 1e3:.2f}-{tres.h.max() * 1e3:.2f} mm)  {clock.eta()}")
            mesh = warp.rest_mesh(tres.h)
            prev = [TargetResult(p, x, 0.0, 0.0, 0, True, 0, [], 0.0, strain_weight=float(w))
                    for p, x, w in zip(P, tres.xs, W, strict=True)]
            ares = self._actuation(mesh, prev, None, f"outer {outer}: actuation", clock)
            a_obj = float(sum(r.match for r in ares))
            improved = (total - a_obj) > s.tol * total
            self.say(f"[clone] outer {outer}: objective {total:.4g} -> {a_obj:.4g} "
                     f"({time.perf_counter() - t_it:.0f}s)  {clock.eta()}")
            if a_obj <= total:
                h, P, X = tres.h, np.array([r.p for r in ares]), np.array([r.x for r in ares])
                W = np.array([r.strain_weight for r in ares])
            else:  # worse (e.g. the constraint took back what the thickness step gained): keep the previous design
                self.say(f"[clone] outer {outer}: worse than before; keeping the previous thickness and actuation")
            thickness_gain = (total - t_obj) / max(total, 1e-300)
            actuation_gain = (t_obj - a_obj) / max(total, 1e-300)
            state["log"] = [*state["log"], {"stage": "outer", "outer": outer, "objective": a_obj,
                                                  "thickness_objective": t_obj, "seconds": time.perf_counter() - t_it,
                                                  "thickness_gain": thickness_gain, "actuation_gain": actuation_gain,
                                                  "thickness_iterations": tres.iterations,
                                                  "thickness_log": tres.log, "thickness_reachability": split}]
            total = min(total, a_obj)
            state.update(stage="outer" if improved else "done", outer=outer, h=h, P=P, X=X, W=W,
                         seconds=float(state["seconds"]) + time.perf_counter() - t_it)
            self._save(state)
            if not improved:
                self.say(f"[clone] outer {outer}: neither thickness nor actuation improved by more than "
                         f"{s.tol:.1%}: stopping")
                break
        if "h" not in state:
            state.update(h=h, P=P, X=X, W=W)
        state["warp"] = warp
        state["h0"] = h0
        return state


def _split(entry: dict) -> dict:
    """The reachability split of a thickness log entry: per target the matching term and its first-order residual."""
    match = np.asarray(entry.get("match_per_pose", []), dtype=np.float64)
    resid = np.asarray(entry.get("reachability_residual_per_pose", []), dtype=np.float64)
    total = float(match.sum())
    share = float((total - resid.sum()) / total) if total > 0 else 0.0
    return {"match_per_target": match.tolist(), "residual_per_target": resid.tolist(),
            "reachable_share": share}


def clock_elapsed(t0: float) -> float:
    return time.perf_counter() - t0


def _jsonable(settings: CloneSettings) -> dict:
    return json.loads(json.dumps(asdict(settings)))
