"""The face-cloning report: errors before/after, strain range, predictor disagreement, reachability, pictures, and
the optimized skin as a head asset (``DIR/skin/``, loadable by ``likeness offline simulate/dataset/train``).

Surface errors are given two ways: ``vertex`` (distance between corresponding vertices, the optimized objective)
and ``surface`` (distance from each simulated vertex to the closest point of the target surface, the paper's
convention for its error maps). The goals are judged on the ``surface`` figures and the vertex ones are reported
beside them. The strain measure is the runtime guard's (``models.strain_guard.SurfaceStrain``: principal strain of
the outer surface, smoothed over the guard's radius, triangles within the guard's band of a rigid attachment rim
left out); the unsmoothed single-triangle extremes over the whole surface, rims included, are reported beside it.
"""

from __future__ import annotations

import hashlib
import json
import platform
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from .clone import CloneRun, surface_distances, vertex_errors
from .clone_regions import region_errors, region_summary, thickness_change, thickness_change_picture

MM = 1e3


def _sha256(path: Path | None) -> str | None:
    if path is None or not Path(path).is_file():
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _strain_surface(run: CloneRun, mesh):
    from .strain_constraint import face_strain_surface

    return face_strain_surface(run.face, mesh)


def _strain(surf, x_outer: np.ndarray) -> dict:
    lo, hi = surf.extremes(x_outer)
    eps = surf.triangle_strains(x_outer)
    return {"measure": [lo, hi], "single_triangle_all": [float(np.nanmin(eps[:, 0])), float(np.nanmax(eps[:, 1]))]}


def _rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Best rigid motion (R, t) taking points a to b, and its RMS residual."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1, 1, d]) @ U.T
    t = cb - R @ ca
    res = float(np.sqrt(np.mean(np.sum((a @ R.T + t - b) ** 2, axis=1))))
    return R, t, res


def reachability(run: CloneRun, k: int, x_outer: np.ndarray, err: np.ndarray) -> dict:
    """Where target k's residual sits and what link layout change would reach it.

    Per link patch (outer vertices labelled with the link): RMS error at the optimum and the RMS error a free rigid
    motion of that patch would leave (Kabsch fit of rest → target). A patch whose optimum error is far above its
    rigid-fit error cannot follow the target along its actuators' path through m(p): more degrees of freedom (or a
    moved pivot) for that link would reach it. A worst region in free skin far from any link asks for a new
    attachment there.
    """
    from scipy.spatial.transform import Rotation

    names, labels = run.face.skin.surface_regions()
    rest = run.rest_outer
    q = run.targets[k]
    worst = int(np.argmax(err))
    out: dict[str, Any] = {"worst_vertex_region": names[labels[worst]], "worst_vertex_rest_m": rest[worst].tolist(),
                           "links": {}}
    proposals = []
    for j, name in enumerate(names):
        m = labels == j
        if name in ("free", run.face.skin.spec.skull_set) or m.sum() < 3:
            continue
        rms_opt = float(np.sqrt(np.mean(np.sum((x_outer[m] - q[m]) ** 2, axis=1))))
        R, t, rms_rigid = _rigid_fit(rest[m], q[m])
        rot = Rotation.from_matrix(R).as_rotvec()
        out["links"][name] = {"rms_at_optimum_m": rms_opt, "rms_best_rigid_m": rms_rigid}
        if rms_opt > max(2.0 * rms_rigid, 1e-3):
            c = rest[m].mean(axis=0)
            move = R @ c + t - c
            proposals.append(
                f"link '{name}': its patch stays {rms_opt * MM:.1f} mm RMS from the target at the best actuation, "
                f"while a free rigid motion of the patch would leave {rms_rigid * MM:.1f} mm; the target moves the "
                f"patch centre by ({move[0] * MM:.1f}, {move[1] * MM:.1f}, {move[2] * MM:.1f}) mm and turns it "
                f"{np.degrees(np.linalg.norm(rot)):.1f}° about ({rot[0]:.2f}, {rot[1]:.2f}, {rot[2]:.2f})/|r|: "
                "give this link that motion (another degree of freedom or a moved pivot)")
    fm = labels == names.index("free") if "free" in names else np.zeros(len(labels), bool)
    if fm.any() and err[fm].max() >= 0.99 * err.max():
        bad = fm & (err > 0.5 * err.max())
        c = rest[bad].mean(axis=0)
        proposals.append(f"free skin around ({c[0] * MM:.0f}, {c[1] * MM:.0f}, {c[2] * MM:.0f}) mm "
                         f"({int(bad.sum())} vertices with more than half the worst error) follows no link: an "
                         "attachment under it, or a wider neighbouring link patch, would reach it")
    out["proposals"] = proposals
    return out


def front_view(run: CloneRun) -> np.ndarray:
    """Outer-surface vertices (V, 2) in mm seen from the front: the casting frame's x (the head's left-right axis)
    and y, with the face looking at the viewer."""
    from .mold import casting_frame

    R = casting_frame(run.rest_outer, run.face.faces)
    return (run.rest_outer - run.rest_outer.mean(axis=0)) @ R[:2].T * MM


def strain_limited(run: CloneRun, problem, surf, p_opt: np.ndarray, x_opt: np.ndarray, lo: float, hi: float,
                   steps: int = 6) -> dict:
    """The pose pulled back from the optimum toward neutral (bisection on the straight line in actuator space, as
    the runtime's guard does) until the strain measure is inside [lo, hi]; its errors and strain."""
    from .actuation import simulate

    neutral = problem.space.neutral
    a, b = 0.0, 1.0
    best = (0.0, np.asarray(problem.mesh.nodes, dtype=np.float64))
    x_prev = x_opt
    for _ in range(steps):
        t = 0.5 * (a + b)
        x = simulate(problem, neutral + t * (p_opt - neutral), x_prev)
        if x is None:
            b = t
            continue
        e_lo, e_hi = surf.extremes(x[run.face.outer])
        if lo <= e_lo and e_hi <= hi:
            a, best = t, (t, x)
        else:
            b = t
        x_prev = x
    return {"fraction_of_optimum": best[0], "x": best[1], "p": neutral + best[0] * (p_opt - neutral)}


def error_map(path: Path, run: CloneRun, name: str, panels: list[tuple[str, np.ndarray]]) -> None:
    """Front view of the face coloured by per-vertex surface error (0–4 mm), one panel per stage."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    uv = front_view(run)
    fig, axs = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 4.2), constrained_layout=True,
                            squeeze=False)
    for ax, (title, err) in zip(axs[0], panels, strict=True):
        tc = ax.tripcolor(uv[:, 0], uv[:, 1], run.face.faces, err * MM, shading="gouraud", cmap="jet",
                          vmin=0.0, vmax=4.0)
        ax.set_title(f"{title}\nmean {err.mean() * MM:.2f} max {err.max() * MM:.2f} mm", fontsize=9)
        ax.set_aspect("equal")
        ax.set_axis_off()
    fig.colorbar(tc, ax=axs[0].tolist(), label="surface error (mm), 0–4 mm scale", shrink=0.8)
    fig.suptitle(name)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_skin_asset(run: CloneRun, mesh, folder: Path, provenance: dict) -> None:
    """``folder/skin.vtu`` (the optimized rest mesh, same node sets) and ``face_units.npz`` (unchanged: the outer
    surface is the design's fixed side), plus a README and ``mesh_report.json`` with the provenance."""
    from offline.fem import save_mesh

    folder.mkdir(parents=True, exist_ok=True)
    if mesh.order == 2:  # the asset is the corner mesh (linear nodes first), as the input skin was
        from offline.fem import TetMesh

        n = int(np.asarray(mesh.tets)[:, :4].max()) + 1
        mesh = TetMesh(np.asarray(mesh.nodes)[:n], np.asarray(mesh.tets)[:, :4],
                       {k: np.asarray(v)[np.asarray(v) < n] for k, v in mesh.node_sets.items()})
    save_mesh(folder / "skin.vtu", mesh)
    shutil.copyfile(run.face.mesh_dir / "face_units.npz", folder / "face_units.npz")
    src = run.face.mesh_dir / "mesh_report.json"
    base = json.loads(src.read_text()) if src.exists() else {}
    base["clone"] = provenance
    (folder / "mesh_report.json").write_text(json.dumps(base, indent=1, default=float))
    (folder / "README.md").write_text(
        "# Optimized skin (likeness offline clone)\n\n"
        "- `skin.vtu`: the rest mesh with the optimized thickness (outer surface and attachments unchanged), "
        "node sets as in the input skin.\n"
        "- `face_units.npz`: the face units on the outer surface (copied: the outer surface is unchanged).\n"
        "- `mesh_report.json`: the input skin's report plus `clone` (the design's settings, heights and hashes).\n\n"
        "Use it like the sample skin: `likeness offline simulate --mesh THIS_FOLDER ...`, "
        "`likeness offline dataset --config HEAD --mesh THIS_FOLDER ...`.\n")


def write_report(run: CloneRun, state: dict, inputs: dict[str, Path | None]) -> dict:
    """Compute the figures, write ``report.json``, the error maps and ``skin/``; returns the report."""
    s = run.settings
    out = run.out
    out.mkdir(parents=True, exist_ok=True)
    face = run.face
    warp, h = state["warp"], np.asarray(state["h"])
    mesh_after = warp.rest_mesh(h)
    surf_before = _strain_surface(run, face.mesh)
    surf_after = _strain_surface(run, mesh_after)
    names = run.target_names
    head = face.skin.head
    unit = {a.name: a for a in head.actuators}
    X_pred = np.asarray(state["X_pred"])
    P_pred = np.asarray(state["P_pred"])
    rows = []
    maps = out / "error_maps"
    maps.mkdir(exist_ok=True)
    for k, name in enumerate(names):
        q = run.targets[k]
        xb = np.asarray(state["X_before"][k])[face.outer]
        xa = np.asarray(state["X"][k])[face.outer]
        sb, sa = surface_distances(xb, q, face.faces), surface_distances(xa, q, face.faces)
        vb, va = vertex_errors(xb, q), vertex_errors(xa, q)
        row: dict[str, Any] = {
            "name": name, "weights": run.target_weights[name],
            "before": {"surface_mean_m": float(sb.mean()), "surface_max_m": float(sb.max()),
                       "vertex_mean_m": float(vb.mean()), "vertex_max_m": float(vb.max()),
                       "strain": _strain(surf_before, xb)},
            "after": {"surface_mean_m": float(sa.mean()), "surface_max_m": float(sa.max()),
                      "vertex_mean_m": float(va.mean()), "vertex_max_m": float(va.max()),
                      "strain": _strain(surf_after, xa)},
            "actuation_before": {n: unit[n].to_config_units(float(v)) for n, v in
                                 zip(head.actuator_names, state["P_before"][k], strict=True)},
            "actuation_after": {n: unit[n].to_config_units(float(v)) for n, v in
                                zip(head.actuator_names, state["P"][k], strict=True)},
        }
        row["regions"] = region_errors(run, sb, sa)
        panels = [("uniform skin, actuation optimized", sb), ("thickness + actuation optimized", sa)]
        if X_pred.size and np.all(np.isfinite(X_pred[k])):
            xp = X_pred[k][face.outer]
            sp_ = surface_distances(xp, q, face.faces)
            vp = vertex_errors(xp, q)
            dp = {n: unit[n].to_config_units(float(a - b)) for n, a, b in
                  zip(head.actuator_names, state["P_before"][k], P_pred[k], strict=True)}
            row["predictor_inverse"] = {
                "surface_mean_m": float(sp_.mean()), "surface_max_m": float(sp_.max()),
                "vertex_mean_m": float(vp.mean()), "vertex_max_m": float(vp.max()),
                "strain": _strain(surf_before, xp),
                "actuation": {n: unit[n].to_config_units(float(v)) for n, v in
                              zip(head.actuator_names, P_pred[k], strict=True)},
                "fem_minus_predictor_config_units": dp,
                "max_abs_difference_config_units": float(max(abs(v) for v in dp.values())),
            }
            panels.insert(0, ("runtime predictor inverse (FEM)", sp_))
        lo_v, hi_v = _validated_range(head)
        for stage in ("before", "after"):
            m_lo, m_hi = row[stage]["strain"]["measure"]
            row[stage]["strain_inside_validated_range"] = bool(lo_v <= m_lo and m_hi <= hi_v)
        if "W" in state:
            row["strain_penalty_weight"] = {"before": float(np.asarray(state["W_before"])[k]),
                                            "after": float(np.asarray(state["W"])[k])}
        if not row["after"]["strain_inside_validated_range"]:
            lim = strain_limited(run, run.problem.with_mesh(mesh_after), surf_after, np.asarray(state["P"][k]),
                                 np.asarray(state["X"][k]), lo_v, hi_v)
            xl = lim["x"][face.outer]
            sl = surface_distances(xl, q, face.faces)
            row["after_strain_limited"] = {
                "fraction_of_optimum": lim["fraction_of_optimum"], "surface_mean_m": float(sl.mean()),
                "surface_max_m": float(sl.max()), "strain": _strain(surf_after, xl),
                "actuation": {n: unit[n].to_config_units(float(v)) for n, v in
                              zip(head.actuator_names, lim["p"], strict=True)}}
            panels.append(("strain-limited (guard's pull-back)", sl))
        reach_ok = sa.max() <= s.goal_max_m
        row["reached"] = bool(reach_ok)
        if not reach_ok:
            row["reachability"] = reachability(run, k, xa, sa)
        fn = maps / f"{k:02d}_{name}.png"
        error_map(fn, run, name, panels)
        row["error_map"] = str(fn.relative_to(out))
        rows.append(row)
    lo_v, hi_v = _validated_range(head)

    def agg(stage: str, key: str, fn) -> float:
        return float(fn([r[stage][key] for r in rows]))

    summary = {
        "before": {"surface_mean_m": agg("before", "surface_mean_m", np.mean),
                   "surface_max_m": agg("before", "surface_max_m", np.max),
                   "vertex_mean_m": agg("before", "vertex_mean_m", np.mean),
                   "vertex_max_m": agg("before", "vertex_max_m", np.max)},
        "after": {"surface_mean_m": agg("after", "surface_mean_m", np.mean),
                  "surface_max_m": agg("after", "surface_max_m", np.max),
                  "vertex_mean_m": agg("after", "vertex_mean_m", np.mean),
                  "vertex_max_m": agg("after", "vertex_max_m", np.max)},
    }
    if all("predictor_inverse" in r for r in rows):
        summary["predictor_inverse"] = {
            "surface_mean_m": float(np.mean([r["predictor_inverse"]["surface_mean_m"] for r in rows])),
            "surface_max_m": float(np.max([r["predictor_inverse"]["surface_max_m"] for r in rows])),
            "max_abs_actuator_difference_config_units": float(
                np.max([r["predictor_inverse"]["max_abs_difference_config_units"] for r in rows]))}
    strain_before = np.array([r["before"]["strain"]["measure"] for r in rows])
    summary["strain_before"] = {"measure_min": float(strain_before[:, 0].min()),
                                "measure_max": float(strain_before[:, 1].max()),
                                "validated_range": [lo_v, hi_v],
                                "inside": bool(strain_before[:, 0].min() >= lo_v and strain_before[:, 1].max() <= hi_v)}
    strain_after = np.array([r["after"]["strain"]["measure"] for r in rows])
    summary["strain_after"] = {"measure_min": float(strain_after[:, 0].min()),
                               "measure_max": float(strain_after[:, 1].max()),
                               "validated_range": [lo_v, hi_v],
                               "inside": bool(strain_after[:, 0].min() >= lo_v and strain_after[:, 1].max() <= hi_v)}
    limited = [r.get("after_strain_limited", r["after"]) for r in rows]
    summary["after_strain_limited"] = {
        "surface_mean_m": float(np.mean([r["surface_mean_m"] for r in limited])),
        "surface_max_m": float(np.max([r["surface_max_m"] for r in limited])),
        "targets_pulled_back": [r["name"] for r in rows if "after_strain_limited" in r]}
    summary["goals"] = {"mean_m": s.goal_mean_m, "max_m": s.goal_max_m,
                        "mean_met": summary["after"]["surface_mean_m"] <= s.goal_mean_m,
                        "max_met": summary["after"]["surface_max_m"] <= s.goal_max_m}
    summary["unreached_targets"] = [r["name"] for r in rows if not r["reached"]]
    summary["regions"] = region_summary(rows, s.goal_mean_m)
    _, dh_stats = thickness_change(warp, face, np.asarray(state["h0"]), h)
    summary["thickness_change"] = dh_stats
    hashes = {k: _sha256(v) for k, v in inputs.items()}
    provenance = {"settings": state["settings"], "heights_m": h.tolist(), "samples_uv_m": warp.samples_uv.tolist(),
                  "mls_width_m": warp.width, "inputs_sha256": hashes}
    write_skin_asset(run, mesh_after, out / "skin", provenance)
    thickness_picture(out / "thickness.png", run, warp, np.asarray(state["h0"]), h)
    thickness_change_picture(out / "thickness_change.png", run, warp, np.asarray(state["h0"]), h)
    report = {
        "head": str(head.source), "mesh": str(face.mesh_dir), "n_nodes": int(face.mesh.n_nodes),
        "n_tets": int(face.mesh.n_tets), "targets": rows, "summary": summary,
        "strain_measure": {"kind": "runtime skin-strain guard measure (models.strain_guard.SurfaceStrain)",
                           "radius_m": surf_after.radius, "band_m": surf_after.band,
                           "rims": "triangles whose centroid lies within band_m of a rigid attachment region (link "
                                   "patches and skull, measured through the skin) are left out of the measure; "
                                   "single_triangle_all gives the raw per-triangle extremes including them",
                           "kept_area_fraction": surf_after.kept_area_fraction},
        "strain_constraint": _constraint_info(run),
        "thickness": {"h_min_m": s.h_min, "h_max_m": s.h_max, "start_m": np.asarray(state["h0"]).tolist(),
                      "after_m": h.tolist(), "samples_uv_m": warp.samples_uv.tolist(), "mls_width_m": warp.width,
                      "change": dh_stats, "change_picture": "thickness_change.png",
                      "design_element_order": int(face.mesh.order), "design_n_nodes": int(face.mesh.n_nodes),
                      "reachability": [e["thickness_reachability"] for e in state["log"]
                                       if "thickness_reachability" in e]},
        "log": state["log"], "outer_iterations": int(state.get("outer", 0)),
        "seconds": float(state.get("seconds", 0.0)),
        "settings": state["settings"], "inputs_sha256": hashes,
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
        "skin_asset": "skin/", "thickness_picture": "thickness.png",
    }
    (out / "report.json").write_text(json.dumps(report, indent=1, default=float))
    return report


def _constraint_info(run: CloneRun) -> dict:
    con = run.problem.strain
    if con is None:
        return {"enabled": False, "note": "poses were optimized without the strain constraint "
                                          "(--no-strain-constraint); poses outside the range are pulled back"}
    return {"enabled": True, "strain_min": con.strain_min, "strain_max": con.strain_max, "margin": con.margin,
            "starting_weight": con.weight, "growth": con.growth, "max_rounds": con.max_rounds,
            "method": "hinge penalty ½ w Σ_k max(0, f_k − limit ∓ margin)² over every kept patch k of the guard's "
                      "smoothed principal strains (both sides), its residuals Gauss-Newton rows with analytic "
                      "derivatives chained through the FEM sensitivities dx/dp; w grows until the exact guard measure "
                      "(SurfaceStrain.extremes) of the optimum is inside [strain_min, strain_max]. The thickness step "
                      "does not see it; the actuation step after it restores it on the new rest shape."}


def _validated_range(head) -> tuple[float, float]:
    from models.strain_guard import skin_strain_range

    return skin_strain_range(head)


def thickness_picture(path: Path, run: CloneRun, warp, h0: np.ndarray, h: np.ndarray) -> None:
    """Front view of the skin's thickness (outer vertex to nearest inner vertex) before and after."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.spatial import cKDTree

    uv = front_view(run)
    vals = []
    for hh in (h0, h):
        X = warp.rest_positions(hh)
        d, _ = cKDTree(X[run.face.inner]).query(X[run.face.outer])
        vals.append(d * MM)
    vmax = max(v.max() for v in vals)
    fig, axs = plt.subplots(1, 2, figsize=(8, 4.2), constrained_layout=True)
    for ax, title, v in zip(axs, ("uniform (as meshed)", "optimized"), vals, strict=True):
        tc = ax.tripcolor(uv[:, 0], uv[:, 1], run.face.faces, v, shading="gouraud", cmap="viridis", vmin=0,
                          vmax=vmax)
        ax.set_title(f"skin thickness, {title}", fontsize=9)
        ax.set_aspect("equal")
        ax.set_axis_off()
    fig.colorbar(tc, ax=axs.tolist(), label="thickness (mm)", shrink=0.8)
    fig.savefig(path, dpi=90)
    plt.close(fig)
