"""Ground-truth recovery of a thickness field: the validation of the thickness optimization.

A block of silicone gets a random MLS thickness field; its two end faces are attachments (one clamped, the other
moved rigidly: stretch, lift, twist, sideways shear, magnitudes drawn from the seed); the simulated top surfaces
are the targets. Starting from the uniform block the optimizer must find the field again.
"""

from __future__ import annotations

import hashlib
import json
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from offline.fem import box_mesh, neo_hookean_from_E_nu, to_quadratic
from offline.fem.solve import rigid_transform_dirichlet

from .thickness import Pose, ThicknessProblem, optimize_adjoint, optimize_joint, solve_poses
from .warp import ThicknessWarp, block_warp


@dataclass(frozen=True)
class BlockSettings:
    """Size of the block test. ``default()`` is the documented run; ``quick()`` the test-size one."""

    size_m: tuple[float, float, float] = (0.095, 0.025, 0.006)
    divisions: tuple[int, int, int] = (38, 10, 3)
    n_samples: int = 16
    n_poses: int = 4
    variation: float = 0.25  # true heights drawn in h0 · [1 − v, 1 + v]
    youngs_modulus_pa: float = 1.0e5
    poisson: float = 0.45
    method: str = "gauss-newton"  # adjoint step: gauss-newton | lbfgs; or "joint"
    max_iterations: int = 40
    element_order: int = 1  # 1: linear tets, 2: quadratic tets (same corner mesh, mid-edge nodes added)

    @staticmethod
    def default() -> BlockSettings:
        """The documented run: a 95 × 25 × 6 mm bar (6,840 tets), 16 samples, 4 poses."""
        return BlockSettings()

    @staticmethod
    def quick() -> BlockSettings:
        """Test size: 60 × 25 × 6 mm (576 tets), 6 samples, 3 poses."""
        return BlockSettings(size_m=(0.06, 0.025, 0.006), divisions=(12, 4, 2), n_samples=6, n_poses=3)


def _rot_x(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def imposed_motions(size: tuple[float, float, float], n_poses: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Rigid 4x4 motions of the x1 end face: stretch, lift with a bend, twist, sideways shear (cycled)."""
    lx, ly, lz = size
    centre = np.array([lx, ly / 2, lz / 2])
    out = []
    for k in range(n_poses):
        R, tr = np.eye(3), np.zeros(3)
        kind = k % 4
        if kind == 0:
            tr = np.array([rng.uniform(0.10, 0.20) * lx, 0.0, 0.0])
        elif kind == 1:
            tr = np.array([0.0, 0.0, rng.uniform(0.12, 0.22) * lx])
            R = _rot_y(-rng.uniform(0.15, 0.3))
        elif kind == 2:
            R = _rot_x(rng.uniform(0.3, 0.5) * (1 if rng.random() < 0.5 else -1))
        else:
            tr = np.array([0.0, rng.uniform(0.10, 0.2) * lx, 0.0])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ centre + tr
        out.append(T)
    return out


def _problem(warp: ThicknessWarp, settings: BlockSettings, motions, targets) -> ThicknessProblem:
    mesh = warp.mesh
    material = neo_hookean_from_E_nu(settings.youngs_modulus_pa, settings.poisson)
    region = np.asarray(mesh.node_sets["z1"])
    poses = tuple(Pose(rigid_transform_dirichlet(mesh, {"x1": T}, fixed_sets=("x0",)), q)
                  for T, q in zip(motions, targets, strict=True))
    lz = settings.size_m[2]
    return ThicknessProblem(warp, material, poses, region, h_min=0.4 * lz, h_max=1.6 * lz)


def block_problem(settings: BlockSettings, seed: int = 0) -> tuple[ThicknessProblem, np.ndarray, list[np.ndarray]]:
    """The recovery problem: (problem whose targets come from the true field, true heights, end-face motions)."""
    rng = np.random.default_rng(seed)
    mesh = box_mesh(settings.size_m, settings.divisions)
    if settings.element_order not in (1, 2):
        raise ValueError(f"element_order must be 1 or 2, got {settings.element_order}")
    if settings.element_order == 2:
        mesh = to_quadratic(mesh)
    warp = block_warp(mesh, n_samples=settings.n_samples)
    lz = settings.size_m[2]
    h_true = lz * (1.0 + settings.variation * rng.uniform(-1.0, 1.0, settings.n_samples))
    motions = imposed_motions(settings.size_m, settings.n_poses, rng)
    region = np.asarray(mesh.node_sets["z1"])
    placeholder = [np.zeros((region.size, 3))] * settings.n_poses  # the forward simulation needs no targets
    true_problem = _problem(warp, settings, motions, placeholder)
    true_state = solve_poses(true_problem, true_problem.check_heights(h_true))
    if true_state is None:
        raise RuntimeError("the ground-truth block did not solve; lower the variation or the motions")
    targets = [x[region] for x in true_state.xs]
    return _problem(warp, settings, motions, targets), h_true, motions


def run_ground_truth(settings: BlockSettings, seed: int = 0, verbose: bool = False) -> dict:
    """Make targets from a random thickness field and recover it from the uniform block; returns the report dict
    plus private arrays (keys starting with ``_``) for the pictures."""
    problem, h_true, motions = block_problem(settings, seed)
    warp, mesh, region = problem.warp, problem.warp.mesh, problem.region
    targets = [p.target for p in problem.poses]
    lz = settings.size_m[2]
    h0 = np.full(settings.n_samples, lz)
    t0 = time.perf_counter()
    if settings.method == "joint":
        res = optimize_joint(problem, h0, max_iterations=settings.max_iterations, verbose=verbose)
    else:
        res = optimize_adjoint(problem, h0, method=settings.method, max_iterations=settings.max_iterations,
                               verbose=verbose)
    seconds = time.perf_counter() - t0
    start = _initial_states(problem, h0)
    err_before = _surface_errors(start, targets, region)
    err_after = _surface_errors(res.xs, targets, region)
    rel = np.abs(res.h - h_true) / h_true
    report = {
        "seed": seed,
        "settings": asdict(settings),
        "method": res.method,
        "n_nodes": mesh.n_nodes,
        "n_tets": mesh.n_tets,
        "samples_uv_m": warp.samples_uv.tolist(),
        "mls_width_m": warp.width,
        "h_true_m": h_true.tolist(),
        "h_start_m": h0.tolist(),
        "h_found_m": res.h.tolist(),
        "height_rel_error_max": float(rel.max()),
        "surface_error_max_m": float(max(e.max() for e in err_after)),
        "surface_error_mean_m": float(np.mean(np.concatenate(err_after))),
        "surface_error_before_max_m": float(max(e.max() for e in err_before)),
        "surface_error_before_mean_m": float(np.mean(np.concatenate(err_before))),
        "iterations": res.iterations,
        "converged": res.converged,
        "forward_pose_solves": res.forward_solves,
        "optimize_seconds": seconds,
        "objective_log": res.log,
        "motions": [T.tolist() for T in motions],
        "inputs_sha256": _hash_inputs(mesh.nodes, mesh.tets, warp.samples_uv, h_true, motions),
        "python": platform.python_version(),
        "_mesh": mesh, "_warp": warp, "_h_true": h_true, "_h0": h0, "_h": res.h,
        "_err_before": err_before, "_err_after": err_after, "_region": region, "_targets": targets,
        "_xs_after": res.xs, "_xs_before": start,
    }
    return report


def _initial_states(problem: ThicknessProblem, h0: np.ndarray) -> list[np.ndarray]:
    return solve_poses(problem, h0).xs


def _surface_errors(xs, targets, region) -> list[np.ndarray]:
    return [np.linalg.norm(x[region] - q, axis=1) for x, q in zip(xs, targets, strict=True)]


def _hash_inputs(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if isinstance(a, list):
            for b in a:
                h.update(np.ascontiguousarray(b, dtype=np.float64).tobytes())
        else:
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def thickness_map(warp: ThicknessWarp, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the inner-surface nodes and the block's thickness there for heights h (for pictures)."""
    mesh = warp.mesh
    inner = np.asarray(mesh.node_sets["z0"])
    X = warp.rest_positions(h)
    top = float(np.asarray(mesh.nodes)[:, 2].max())
    return X[inner, :2], top - X[inner, 2]


def write_outputs(report: dict, out_dir: Path) -> dict:
    """Write ``report.json`` and the before/after PNGs into ``out_dir``; returns the JSON-able report."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    warp = report["_warp"]
    mm = 1e3
    maps = [("start (uniform)", report["_h0"]), ("recovered", report["_h"]), ("ground truth", report["_h_true"])]
    vals = [thickness_map(warp, h) for _, h in maps]
    vmin = min(v[1].min() for v in vals) * mm
    vmax = max(v[1].max() for v in vals) * mm
    fig, axes = plt.subplots(3, 1, figsize=(7, 6.5), constrained_layout=True)
    for ax, (title, _), (uv, th) in zip(axes, maps, vals, strict=True):
        tc = ax.tricontourf(uv[:, 0] * mm, uv[:, 1] * mm, th * mm, levels=np.linspace(vmin, vmax, 21),
                            cmap="viridis")
        ax.plot(warp.samples_uv[:, 0] * mm, warp.samples_uv[:, 1] * mm, "k.", ms=4)
        ax.set_title(f"thickness, {title}")
        ax.set_aspect("equal")
        ax.set_ylabel("y (mm)")
    axes[-1].set_xlabel("x (mm)")
    fig.colorbar(tc, ax=axes, label="thickness (mm)")
    fig.savefig(out_dir / "thickness.png", dpi=110)
    plt.close(fig)

    region = report["_region"]
    X0 = np.asarray(report["_mesh"].nodes)[region]
    n = len(report["_err_before"])
    fig, axes = plt.subplots(n, 2, figsize=(10, 2.0 * n + 0.6), constrained_layout=True, squeeze=False)
    emax = max(e.max() for e in report["_err_before"]) * mm
    for k in range(n):
        for j, (label, errs) in enumerate((("before (uniform)", report["_err_before"]),
                                           ("after", report["_err_after"]))):
            ax = axes[k, j]
            sc = ax.scatter(X0[:, 0] * mm, X0[:, 1] * mm, c=errs[k] * mm, cmap="magma", vmin=0, vmax=emax, s=12)
            ax.set_title(f"pose {k}: surface error {label}, max {errs[k].max() * mm:.4f} mm", fontsize=9)
            ax.set_aspect("equal")
    fig.colorbar(sc, ax=axes, label="|x − target| (mm)")
    fig.savefig(out_dir / "surface_error.png", dpi=110)
    plt.close(fig)

    fig = plt.figure(figsize=(9, 3.2 * ((n + 1) // 2)))
    for k in range(n):
        ax = fig.add_subplot((n + 1) // 2, 2, k + 1, projection="3d")
        q = report["_targets"][k] * mm
        xb = report["_xs_before"][k][region] * mm
        xa = report["_xs_after"][k][region] * mm
        ax.scatter(q[:, 0], q[:, 1], q[:, 2], s=6, c="k", label="target")
        ax.scatter(xb[:, 0], xb[:, 1], xb[:, 2], s=4, c="tab:red", label="uniform block")
        ax.scatter(xa[:, 0], xa[:, 1], xa[:, 2], s=2, c="tab:green", label="optimized")
        ax.set_title(f"pose {k} (top surface, mm)", fontsize=9)
        if k == 0:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "poses.png", dpi=100)
    plt.close(fig)

    public = {k: v for k, v in report.items() if not k.startswith("_")}
    public["pictures"] = ["thickness.png", "surface_error.png", "poses.png"]
    (out_dir / "report.json").write_text(json.dumps(public, indent=2))
    return public
