"""Study: the thickness step on design meshes with more elements through the skin (the shipped one-tet-thick skin
against its layered extrusions, :mod:`offline.design.layered`).

Starts from a finished ``likeness offline clone`` run's checkpoint (``--from DIR``: the actuation optimized on the
uniform shipped skin, stage 2) and, per design mesh, solves the targets at those actuations, places the samples as
clone does, and measures at the start of the thickness step: the first-order share of the matching term that
thickness can remove (:func:`offline.design.thickness.reachability_split`) inside the bounds and with the heights
unbounded, and the bounded best change's size; then whether steps of growing size along that change fold the rest
mesh (inverted elements); then runs the thickness step alone (Gauss-Newton, ``--iterations``) with the actuation
fixed and reports the free-skin surface error of each target before and after. Writes ``OUT/layers_study.json``
(settings, inputs' SHA-256) and prints one line per mesh. Run:
``python benchmarks/thickness_layers.py --from runs/clone --out runs/layers [--layers 0,2,3]`` (0: the shipped mesh).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _free_errors(run, xs: list[np.ndarray]) -> list[float]:
    """Mean surface distance (m) over the free-skin outer vertices, per target."""
    from offline.dataset.regions import FREE
    from offline.design.clone import surface_distances

    names, labels = run.face.skin.surface_regions()
    free = labels == names.index(FREE)
    out = []
    for x, q in zip(xs, run.targets, strict=True):
        d = surface_distances(x[run.face.outer], q, run.face.faces)
        out.append(float(d[free].mean()))
    return out


#: Thickness bounds (mm) at which the first-order removable share is measured: the head's, then wider.
BOUNDS_MM = ((3, 12), (2, 20), (1, 40), (0.5, 100))


def _free_rows(run, tp) -> np.ndarray:
    """Rows of the thickness step's residual that belong to free-skin outer vertices (3 per vertex)."""
    from offline.dataset.regions import FREE
    from offline.design.thickness import _region_dofs

    names, labels = run.face.skin.surface_regions()
    free_vertex = labels == names.index(FREE)
    dofs = _region_dofs(tp)  # the residual's rows: dofs of the matched outer nodes
    node = dofs // 3
    pos = np.full(run.face.mesh.n_nodes, -1)
    pos[run.face.outer] = np.arange(len(run.face.outer))
    return np.flatnonzero(free_vertex[pos[node]])


def _fold_probe(warp, h: np.ndarray, direction: np.ndarray, sizes_mm: list[float]) -> list[dict]:
    """Inverted elements of the warped rest mesh for steps of growing largest |Δh| along ``direction``."""
    from offline.fem.energy import element_min_jacobian

    rows = []
    scale = float(np.abs(direction).max())
    for s in sizes_mm:
        dh = direction * (s * 1e-3 / max(scale, 1e-300))
        J = element_min_jacobian(warp.mesh, warp.rest_positions(h + dh))
        rows.append({"max_abs_dh_mm": s, "inverted_elements": int(np.sum(J <= 0)), "min_jacobian": float(J.min())})
    return rows


def study_mesh(args, layers: int, P: np.ndarray, out: Path) -> dict:
    """Every figure of one design mesh (``layers`` 0: the shipped skin)."""
    from offline.design.actuation import simulate
    from offline.design.clone import CloneRun, CloneSettings, _split
    from offline.design.clone_regions import thickness_change
    from offline.design.face import face_warp, load_face
    from offline.design.layered import layered_skin_folder
    from offline.design.targets import DEFAULT_TARGETS
    from offline.design.thickness import optimize_adjoint, reachability_split, sensitivities, solve_poses
    from offline.design.warp import strain_density

    mesh_dir = None
    if layers:
        mesh_dir = out / f"mesh_{layers}_layers"
        layered_skin_folder(Path(args.config).resolve().parent / "skin", mesh_dir, layers=layers)
    face = load_face(args.config, mesh_dir)
    settings = CloneSettings()
    targets = {n: DEFAULT_TARGETS[n] for n in args.target_names}
    run = CloneRun(face, targets, out / "unused", settings, progress=lambda s: None)
    problem = face.actuation_problem()
    t0 = time.perf_counter()
    xs, prev = [], None
    for p in P:
        x = simulate(problem, p, prev)
        if x is None:
            raise SystemExit(f"{layers} layers: a target pose does not converge at the checkpoint's actuation")
        xs.append(x)
        prev = x
    t_poses = time.perf_counter() - t0
    warp, h0 = face_warp(face, n_samples=settings.n_samples, width_factor=settings.width_factor,
                         density=strain_density(face.mesh, xs))
    tp = run.thickness_problem(warp, P)
    h_start = np.clip(h0, settings.h_min + 1e-5, settings.h_max - 1e-5)
    state = solve_poses(tp, h_start, xs)
    rs, Js = sensitivities(tp, state)
    match = np.array([0.5 * float(r @ r) for r in rs])
    res_b, dh_b = reachability_split(rs, Js, settings.h_min - h_start, settings.h_max - h_start)
    res_u, _ = reachability_split(rs, Js)
    folds = _fold_probe(warp, h_start, dh_b, [1.0, 2.0, 3.0, 4.5, 6.0])
    # what wider bounds would allow, and the share on the free skin alone (link-region rows left out)
    free_rows = _free_rows(run, tp)
    shares = {}
    for lo_mm, hi_mm in BOUNDS_MM:
        lo, hi = lo_mm * 1e-3 - h_start, hi_mm * 1e-3 - h_start
        r_all, _ = reachability_split(rs, Js, lo, hi)
        r_free, _ = reachability_split([r[free_rows] for r in rs], [J[free_rows] for J in Js], lo, hi)
        m_free = sum(0.5 * float(r[free_rows] @ r[free_rows]) for r in rs)
        shares[f"{lo_mm}-{hi_mm} mm"] = {"all": float(1 - r_all.sum() / match.sum()),
                                         "free_skin": float(1 - r_free.sum() / m_free)}
    before = _free_errors(run, list(state.xs))
    t1 = time.perf_counter()
    res = optimize_adjoint(tp, h_start, max_iterations=args.iterations, warm=list(state.xs),
                           tol_gain=settings.tol_gain)
    t_opt = time.perf_counter() - t1
    after = _free_errors(run, list(res.xs))
    _, dh = thickness_change(warp, face, h_start, res.h)
    return {"layers": layers, "nodes": face.mesh.n_nodes, "tets": face.mesh.n_tets,
            "interior_nodes": int(face.mesh.n_nodes - len(face.outer) - len(face.inner)),
            "kernel_width_mm": warp.width * 1e3, "pose_solves_s": t_poses,
            "match_start": float(match.sum()),
            "reachable_share_bounded": float(1 - res_b.sum() / match.sum()),
            "reachable_share_unbounded": float(1 - res_u.sum() / match.sum()),
            "best_bounded_change_max_abs_mm": float(np.abs(dh_b).max() * 1e3),
            "removable_share_by_bounds": shares,
            "fold_probe_along_bounded_change": folds,
            "thickness_step": {"iterations": res.iterations, "seconds": t_opt, "match_before": res.log[0]["match"],
                               "match_after": res.log[-1]["match"],
                               "reachable_share_at_start": _split(res.log[0])["reachable_share"],
                               "thickness_change": dh},
            "free_error_before_m": dict(zip(args.target_names, before, strict=True)),
            "free_error_after_m": dict(zip(args.target_names, after, strict=True)),
            "free_error_mean_before_m": float(np.mean([before[i] for i in args.reach_idx])),
            "free_error_mean_after_m": float(np.mean([after[i] for i in args.reach_idx]))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--from", dest="src", required=True, help="a clone run's output folder (its checkpoint.npz)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--config", default=str(ROOT / "heads" / "sample" / "head.toml"))
    ap.add_argument("--layers", default="0,2,3", help="design meshes: 0 the shipped skin, n its n-layer extrusion")
    ap.add_argument("--iterations", type=int, default=6, help="thickness Gauss-Newton iterations at most")
    args = ap.parse_args(argv)

    from offline.design.clone import CHECKPOINT

    src = Path(args.src)
    with np.load(src / CHECKPOINT) as z:
        meta = json.loads(str(z["meta"]))
        P = np.asarray(z["P_before"])
    report_src = json.loads((src / "report.json").read_text())
    args.target_names = list(meta["targets"])
    reach = report_src["summary"]["regions"]["reachable_targets"]
    args.reach_idx = [args.target_names.index(n) for n in reach]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for layers in (int(v) for v in args.layers.split(",")):
        row = study_mesh(args, layers, P, out)
        rows.append(row)
        b, a = row["free_error_mean_before_m"], row["free_error_mean_after_m"]
        fold = next((f["max_abs_dh_mm"] for f in row["fold_probe_along_bounded_change"]
                     if f["inverted_elements"]), None)
        sh = "; ".join(f"{k}: {v['all']:.1%} / free {v['free_skin']:.1%}"
                       for k, v in row["removable_share_by_bounds"].items())
        print(f"{layers or 'shipped (1)'} layers: {row['nodes']} nodes, {row['tets']} tets; removable share "
              f"(first order) {sh}; unbounded {row['reachable_share_unbounded']:.1%}; first fold along the "
              f"bounded change at |dh| {fold} mm; thickness step {row['thickness_step']['iterations']} it: free "
              f"error on reachable targets {b * 1e3:.3f} -> {a * 1e3:.3f} mm ({1 - a / b:.1%} lower)", flush=True)
        _write(out, args, rows, reach, src)
    print(f"-> {out / 'layers_study.json'}")
    return 0


def _write(out: Path, args, rows: list[dict], reach: list[str], src: Path) -> None:
    """The study's report so far (written after every mesh, so a stopped run keeps what it measured)."""
    from models.atomic import write_text
    from offline.design.clone import CHECKPOINT

    cfg = Path(args.config)
    report = {"rows": rows, "targets": args.target_names, "reachable_targets": reach, "iterations": args.iterations,
              "bounds_mm": BOUNDS_MM, "command": " ".join(sys.argv),
              "inputs_sha256": {"checkpoint": _sha(src / CHECKPOINT), "config": _sha(cfg),
                                "skin_vtu": _sha(cfg.resolve().parent / "skin" / "skin.vtu")}}
    write_text(out / "layers_study.json", json.dumps(report, indent=1, default=float) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
