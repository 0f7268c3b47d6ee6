"""Study: the MLS kernel width of the face's thickness warp — the thickness step's objective after optimization
against the width (as a factor of the mean sample spacing).

Starts from a finished ``likeness offline clone`` run's checkpoint (``--from DIR``: the actuation optimized on the
uniform skin, stage 2), places the samples as the run does (denser where those poses strain the skin most), and
for each width factor runs the thickness step alone (Gauss-Newton to the predicted-gain stop, or
``--iterations``) with the actuation fixed. With ``--element-order 2`` a linear run's states are lifted (mid-edge
nodes at their edges' midpoints) to start the quadratic solves. Writes ``OUT/width_study.json`` (per width: the
kernel width in mm, the matching term before and after, its reachable share at the start, iterations, seconds,
|Δh| figures; the settings and the inputs' SHA-256) and ``OUT/width_study.png``. Run:
``python benchmarks/thickness_width.py --from runs/clone --out runs/width [--factors 0.6,0.9,1.2,1.8]``.
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--from", dest="src", required=True, help="a clone run's output folder (its checkpoint.npz)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--config", default=str(ROOT / "heads" / "sample" / "head.toml"))
    ap.add_argument("--factors", default="0.6,0.9,1.2,1.8", help="kernel widths, × the mean sample spacing")
    ap.add_argument("--iterations", type=int, default=8, help="thickness Gauss-Newton iterations at most")
    ap.add_argument("--element-order", type=int, choices=(1, 2), default=1)
    args = ap.parse_args(argv)

    from dataclasses import replace

    from offline.design.clone import CHECKPOINT, CloneRun, CloneSettings, _split
    from offline.design.clone_regions import thickness_change
    from offline.design.face import face_warp, load_face
    from offline.design.targets import DEFAULT_TARGETS
    from offline.design.thickness import optimize_adjoint
    from offline.design.warp import strain_density

    ck = Path(args.src) / CHECKPOINT
    with np.load(ck) as z:
        meta = json.loads(str(z["meta"]))
        P, X = np.asarray(z["P_before"]), np.asarray(z["X_before"])
    settings = replace(CloneSettings(**{k: v for k, v in meta["settings"].items()
                                        if k in CloneSettings.__dataclass_fields__}),
                       element_order=args.element_order)
    face = load_face(args.config, element_order=args.element_order)
    if args.element_order == 2 and X.shape[1] < face.mesh.n_nodes:  # linear states: mid-edge nodes at midpoints
        from offline.design.warp import _midpoint_map

        n = X.shape[1]
        lift = np.zeros((X.shape[0], face.mesh.n_nodes, 3))
        lift[:, :n] = X
        M = _midpoint_map(face.mesh)
        X = np.stack([M @ x for x in lift])
    if X.shape[1] != face.mesh.n_nodes:
        raise SystemExit(f"{ck}: states have {X.shape[1]} nodes, the skin at order {args.element_order} has "
                         f"{face.mesh.n_nodes}: run the clone at the same --element-order")
    targets = {n: DEFAULT_TARGETS[n] for n in meta["targets"]}
    run = CloneRun(face, targets, Path(args.out) / "unused", settings, progress=lambda s: None)
    density = strain_density(face.mesh, list(X))
    rows = []
    for f in (float(v) for v in args.factors.split(",")):
        warp, h0 = face_warp(face, n_samples=settings.n_samples, width_factor=f, density=density)
        tp = run.thickness_problem(warp, P)
        t0 = time.perf_counter()
        res = optimize_adjoint(tp, np.clip(h0, settings.h_min + 1e-5, settings.h_max - 1e-5),
                               max_iterations=args.iterations, warm=list(X), tol_gain=settings.tol_gain)
        _, dh = thickness_change(warp, face, h0, res.h)
        row = {"width_factor": f, "width_mm": warp.width * 1e3, "match_before": res.log[0]["match"],
               "match_after": res.log[-1]["match"], "reachable_share_at_start": _split(res.log[0])["reachable_share"],
               "match_per_target_before": res.log[0].get("match_per_pose"),
               "reachability_residual_per_target": res.log[0].get("reachability_residual_per_pose"),
               "iterations": res.iterations, "seconds": time.perf_counter() - t0, "thickness_change": dh}
        rows.append(row)
        print(f"width {f:.2f} x spacing = {row['width_mm']:.1f} mm: match {row['match_before']:.4g} -> "
              f"{row['match_after']:.4g} ({1 - row['match_after'] / row['match_before']:.1%} lower), reachable "
              f"share at start {row['reachable_share_at_start']:.1%}, {res.iterations} it, |dh| max "
              f"{dh['abs_max_mm']:.2f} mm, {row['seconds']:.0f} s", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"rows": rows, "n_samples": settings.n_samples, "targets": meta["targets"],
              "element_order": args.element_order, "settings": meta["settings"],
              "inputs_sha256": {"checkpoint": _sha(ck), "config": _sha(Path(args.config)),
                                "skin_vtu": _sha(face.mesh_dir / "skin.vtu")}}
    (out / "width_study.json").write_text(json.dumps(report, indent=1, default=float))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.4), constrained_layout=True)
    w = [r["width_mm"] for r in rows]
    ax.plot(w, [r["match_after"] / r["match_before"] for r in rows], "o-")
    ax.set_xlabel("MLS kernel width (mm)")
    ax.set_ylabel("thickness objective after / before")
    ax.set_title(f"kernel width study ({settings.n_samples} samples, order {args.element_order})", fontsize=9)
    fig.savefig(out / "width_study.png", dpi=100)
    plt.close(fig)
    print(f"-> {out / 'width_study.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
