"""The layout design's report: per target before/after errors and strain, the design parameters that moved, the
envelope limits that bind (and how far they would have to move), pictures of the old and new mechanism, and the
redesigned head folder's checks; written as ``report.json`` and ``report.md`` by the command that computed them.

Binding limits come from the Gauss-Newton model at the final design (actuation included): for each group of design
variables at its bound, the outward slope of the objective (the bound's multiplier) and the step the model takes
when only that bound is lifted (every actuation free, the other design variables held): how far past the limit it
goes, the objective it predicts and each target's predicted RMS surface error.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_text

from .actuation import _objective
from .clone import surface_distances, vertex_errors
from .mechanism_design import LayoutProblem, LayoutState, normal_equations
from .mechanism_design_envelope import VariableGroup

GOAL_MEAN_M = 0.5e-3
GOAL_MAX_M = 4e-3
#: What the free-attachment figures mean (in the report beside them).
BOUND_NOTE = ("Each attachment node set moved by any rigid motion of its own, per target (no mechanism, no "
              "envelope), the actuation optimizer's objective and strain constraint, started from the new layout's "
              "solution: every layout's attachment motions are among these, so a target these motions cannot bring "
              "within the goal is out of reach of every layout with these attachment sets and this skin. The "
              "optimizer is local and lowers the objective (the sum of squared vertex errors, and the strain "
              "penalty), so its mean and max can differ from the layout's in either direction by a little.")


def _sha256(path: str | Path | None) -> str | None:
    if path is None or not Path(path).is_file():
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def target_errors(lp: LayoutProblem, X: np.ndarray) -> list[dict[str, Any]]:
    """Per target: vertex and surface errors (m) and the guard's exact strain measure."""
    face = lp.face
    con = lp.measure
    rest = np.asarray(face.mesh.nodes)[face.outer]
    region_names, labels = face.skin.surface_regions()
    out = []
    for x, q in zip(X, lp.targets, strict=True):
        ev = vertex_errors(x[face.outer], q)
        sd = surface_distances(x[face.outer], q, face.faces)
        i = int(np.argmax(ev))
        row = {"vertex_mean_m": float(ev.mean()), "vertex_max_m": float(ev.max()),
               "surface_mean_m": float(sd.mean()), "surface_max_m": float(sd.max()),
               "vertices_over_4mm": int((ev > GOAL_MAX_M).sum()), "vertices": int(ev.size),
               "worst_vertex": {"index": i, "region": str(region_names[labels[i]]), "rest_m": rest[i].tolist(),
                                "target_moves_it_m": float(np.linalg.norm(q[i] - rest[i]))}}
        if con is not None:
            smin, smax = con.measure(x)
            row.update(strain_min=float(smin), strain_max=float(smax), strain_inside=bool(con.inside((smin, smax))))
        out.append(row)
    return out


def target_strains(lp: LayoutProblem) -> list[tuple[float, float] | None]:
    """The guard's strain measure of each target surface itself (the outer surface placed on the target): a target
    outside the validated range cannot be reached exactly by any pose inside it, whatever the mechanism."""
    con = lp.measure
    x = np.asarray(lp.face.mesh.nodes, dtype=np.float64).copy()
    out = []
    for q in lp.targets:
        x[lp.face.outer] = q
        lo, hi = con.measure(x)
        out.append((float(lo), float(hi)))
    return out


def _group_value(g: VariableGroup, v: np.ndarray, base: float) -> tuple[float, str, float, str]:
    """(size of the move, its unit, the limit, a description) of one group's offsets."""
    if g.kind == "ball":
        n = float(np.linalg.norm(v))
        if g.unit == "deg":
            return math.degrees(n), "deg", math.degrees(g.radius), "tilt"
        return n * 1e3, "mm", g.radius * 1e3, "move"
    rel = float(v[0]) / abs(base) if base else 0.0
    return rel * 100, "%", g.hi / abs(base) * 100 if base else 0.0, "change"


def _base(lp: LayoutProblem, g: VariableGroup) -> float:
    from models.mechanism_file import get_param

    return get_param(lp.space.spec, f"{g.item}.{g.what}") if g.kind == "box" else 0.0


def moved_parameters(lp: LayoutProblem, theta: np.ndarray, tol: float = 1e-6) -> list[dict[str, Any]]:
    """Every group of design variables that moved, largest first relative to its limit."""
    active = {id(g) for g in lp.space.active(theta)}
    rows = []
    for g in lp.space.groups:
        v = theta[list(g.index)]
        if np.max(np.abs(v) / lp.space.scale[list(g.index)]) < tol:
            continue
        base = _base(lp, g)
        size, unit, limit, what = _group_value(g, v, base)
        row = {"item": g.item, "what": g.what, what: size, "unit": unit, "limit": limit, "at_limit": id(g) in active,
               "offset": v.tolist()}
        if g.kind == "box":
            row["from"], row["to"] = base, base + float(v[0])
        rows.append(row)
    rows.sort(key=lambda r: -abs(r.get("move", r.get("tilt", r.get("change", 0.0)))) / max(r["limit"], 1e-12))
    return rows


def binding_limits(lp: LayoutProblem, theta: np.ndarray, Z: np.ndarray, X: np.ndarray, W: np.ndarray,
                   names: Sequence[str]) -> list[dict[str, Any]]:
    """For each design-variable group at its bound: multiplier and the model's step with that bound lifted."""
    active = lp.space.active(theta)
    if not active:
        return []
    lp.boundary.set_design(theta)
    evs = [_objective(lp.problem, z, lp.aspace.expand(z), x, q, float(w))
           for z, x, q, w in zip(Z, X, lp.targets, W, strict=True)]
    lins = [lp.linearize(ev, q) for ev, q in zip(evs, lp.targets, strict=True)]
    g, H = normal_equations(lp, theta, evs, lins)
    K, Zn = Z.shape
    n_z = K * Zn
    s = np.sqrt(1.0 / (lp.problem.region.size * lp.problem.length_scale ** 2))
    out = []
    for grp in active:
        idx = list(grp.index)
        v = theta[idx]
        sel = np.r_[np.arange(n_z), n_z + np.array(idx)]
        Hs, gs = H[np.ix_(sel, sel)], g[sel]
        Hs = Hs + 1e-9 * np.trace(Hs) / len(sel) * np.eye(len(sel))
        d = np.linalg.solve(Hs, -gs)
        dt = d[n_z:]
        gain = -float(gs @ d + 0.5 * d @ Hs @ d)
        base = _base(lp, grp)
        size_now, unit, limit, _ = _group_value(grp, v, base)
        size_new, _, _, _ = _group_value(grp, v + dt, base)
        gt = g[n_z + np.array(idx)]
        if grp.kind == "ball":
            u = v / max(float(np.linalg.norm(v)), 1e-300)
            slope = -float(gt @ u)  # objective decrease per unit of move outward
            per = 1e-3 if grp.unit == "mm" else math.radians(1.0)
        else:
            sign = 1.0 if v[0] > 0 else -1.0
            slope = -float(gt[0]) * sign
            per = abs(base) * 0.01 if base else 1.0
        per_target = []
        for k, lin in enumerate(lins):
            m = lp.problem.region.size * 3
            r_now = lin.r[:m]
            dz = d[k * Zn:(k + 1) * Zn]
            r_new = r_now + lin.Jz[:m] @ dz + lin.Jt[:m][:, idx] @ dt
            rms = [float(np.sqrt(3 * np.mean(r ** 2))) / s * 1e3 for r in (r_now, r_new)]
            per_target.append({"target": names[k], "rms_now_mm": rms[0], "rms_released_mm": rms[1]})
        out.append({"item": grp.item, "what": grp.what, "unit": unit, "limit": limit, "now": size_now,
                    "would_move_to": size_new, "beyond_limit_by": size_new - limit,
                    "objective_slope_per_" + ("mm" if unit == "mm" else "deg" if unit == "deg" else "percent"):
                        slope * per, "predicted_objective_gain": gain, "per_target": per_target})
    out.sort(key=lambda r: -r["predicted_objective_gain"])
    return out


def write_layout_report(lp: LayoutProblem, state: LayoutState, arrays: Mapping[str, np.ndarray], out: Path, *,
                        names: Sequence[str], config: str | Path, targets_file: str | None,
                        envelope: str | Path | None, settings: Mapping[str, Any], seconds: float,
                        head_dir: Path | None, map_samples: int = 300,
                        progress: Callable[[str], None] = print,
                        rings: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Compute the report's figures, write the head folder, the pictures, ``report.json`` and ``report.md``;
    ``rings``: the ring step's limits, per-set summary, rounds and final node sets (None when it did not run)."""
    from .mechanism_design_head import write_head

    before = target_errors(lp, arrays["X_before"])
    after = target_errors(lp, arrays["X_after"])
    bound = target_errors(lp, arrays["X_bound"]) if "X_bound" in arrays else None
    head = lp.face.skin.head
    con = lp.measure
    Z_after = np.array([lp.aspace.reduce(p) for p in arrays["P_after"]])
    progress("[layout] binding limits: the Gauss-Newton model at the final design")
    binding = binding_limits(lp, state.theta, Z_after, arrays["X_after"], arrays["W_after"], names)
    lp.boundary.set_design(state.theta)
    head_checks = None
    if head_dir is not None:
        progress(f"[layout] writing the redesigned head folder {head_dir}")
        head_checks = write_head(config, lp.boundary.dm, head_dir, map_samples=map_samples,
                                 node_sets=None if rings is None else rings["node_sets"],
                                 note="Redesigned by likeness offline clone --design-mechanism (see ../report.md). "
                                      "The predictor and skin guard are the original head's: retrain them on this "
                                      "mechanism (likeness offline dataset / train, likeness offline guard).")
    pictures = _pictures(lp, state.theta, arrays, out, head_checks)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    own = target_strains(lp)
    per_target = []
    for k, name in enumerate(names):
        p = arrays["P_after"][k]
        at = [head.actuator_names[i] for i in range(len(p)) if p[i] <= lo[i] + 1e-6 * (hi[i] - lo[i])
              or p[i] >= hi[i] - 1e-6 * (hi[i] - lo[i])]
        row = {"target": name, "before": before[k], "after": after[k], "actuators_at_limit_after": at,
               "actuation_after_config_units": {a.name: a.to_config_units(float(v))
                                                for a, v in zip(head.actuators, p, strict=True)}}
        if own[k] is not None:
            row["target_strain"] = list(own[k])
            row["target_inside_strain_range"] = bool(con.inside(own[k]))
        reached = after[k]["surface_mean_m"] <= GOAL_MEAN_M and after[k]["surface_max_m"] <= GOAL_MAX_M
        row["reached"] = bool(reached)
        if bound is not None:
            row["bound"] = bound[k]
            row["bound_link_changes"] = _link_changes(lp, arrays["P_after"][k], arrays["P_bound"][k])
            row["bound_reaches_goal"] = bool(bound[k]["surface_mean_m"] <= GOAL_MEAN_M
                                             and bound[k]["surface_max_m"] <= GOAL_MAX_M)
        if not reached:
            row["binding"] = sorted(
                ({"item": b["item"], "what": b["what"], "rms_now_mm": t["rms_now_mm"],
                  "rms_released_mm": t["rms_released_mm"], "beyond_limit_by": b["beyond_limit_by"], "unit": b["unit"]}
                 for b in binding for t in b["per_target"] if t["target"] == name
                 and t["rms_released_mm"] < t["rms_now_mm"] - 1e-3), key=lambda r: r["rms_released_mm"])[:3]
        per_target.append(row)

    def summary(rows: list[dict]) -> dict[str, Any]:
        return {"surface_mean_m": float(np.mean([r["surface_mean_m"] for r in rows])),
                "surface_max_m": float(np.max([r["surface_max_m"] for r in rows])),
                "strain_min": min((r.get("strain_min", 0.0) for r in rows), default=None),
                "strain_max": max((r.get("strain_max", 0.0) for r in rows), default=None),
                "all_inside_strain_range": all(r.get("strain_inside", True) for r in rows)}

    sb, sa = summary(before), summary(after)
    extra = {}
    if bound is not None:
        sbd = summary(bound)
        extra["bound"] = {**sbd, "mean_met": sbd["surface_mean_m"] <= GOAL_MEAN_M,
                          "max_met": sbd["surface_max_m"] <= GOAL_MAX_M,
                          "links": json.loads(str(arrays["bound_links"])),
                          "note": BOUND_NOTE}
    report = {
        "command": "likeness offline clone --design-mechanism",
        "head": head.name, "targets": list(names), "seconds": seconds,
        "inputs_sha256": {"config": _sha256(config), "mechanism": _sha256(head.path("mechanism")),
                          "skin_vtu": _sha256(lp.face.mesh_dir / "skin.vtu"),
                          "face_units": _sha256(lp.face.mesh_dir / "face_units.npz"),
                          "targets": _sha256(targets_file), "envelope": _sha256(envelope)},
        "settings": dict(settings), "envelope": lp.space.envelope.to_json(),
        "design_variables": lp.space.size, "iterations": state.iteration, "log": state.log,
        "strain_range": [con.strain_min, con.strain_max],
        "strain_constraint": lp.problem.strain is not None,
        "summary": {"before": sb, "after": sa,
                    "goal": {"mean_m": GOAL_MEAN_M, "max_m": GOAL_MAX_M,
                             "mean_met": sa["surface_mean_m"] <= GOAL_MEAN_M,
                             "max_met": sa["surface_max_m"] <= GOAL_MAX_M,
                             "strain_met": sa["all_inside_strain_range"]},
                    "unreached_targets": [r["target"] for r in per_target if not r["reached"]], **extra},
        "per_target": per_target, "moved_parameters": moved_parameters(lp, state.theta),
        "binding_limits": binding, "head_folder": head_checks, "pictures": pictures,
    }
    if rings is not None:
        report["attachment_rings"] = {k: v for k, v in rings.items() if k != "node_sets"}
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "report.json", json.dumps(report, indent=1, default=float))
    write_text(out / "report.md", report_markdown(report))
    return report


def _pictures(lp: LayoutProblem, theta: np.ndarray, arrays: Mapping[str, np.ndarray], out: Path,
              head_checks: Mapping[str, Any] | None) -> dict[str, str]:
    """The old and new mechanism over the skin, at neutral (solid) and at the most-open target's actuation."""
    from models.mechanism import Mechanism

    from .mechanism_draw import draw_mechanism

    names = lp.boundary.names
    P = arrays["P_after"]
    k = int(np.argmax(np.abs(P).sum(axis=1)))
    poses = ({}, dict(zip(names, P[k], strict=True)))
    skin = np.asarray(lp.face.mesh.nodes)[lp.face.outer]
    old = Mechanism(lp.space.spec)
    new = Mechanism.load(head_checks["mechanism"]) if head_checks else lp.boundary.dm.mech
    (out / "pictures").mkdir(parents=True, exist_ok=True)
    a = draw_mechanism(old, out / "pictures" / "mechanism_before.png", poses, skin,
                       title="today's mechanism: neutral (solid), the most-open target's actuation (dashed)")
    b = draw_mechanism(new, out / "pictures" / "mechanism_after.png", poses, skin,
                       title="the redesigned mechanism: neutral (solid), the same actuation (dashed)")
    return {"before": str(a), "after": str(b)}


def report_markdown(r: Mapping[str, Any]) -> str:
    """The report as markdown: summary, per-target table, moved parameters, binding limits."""
    mm = 1e3
    s = r["summary"]
    lines = [f"# Link-layout design of head {r['head']}", "",
             f"`{r['command']}`, {len(r['targets'])} targets, {r['design_variables']} design variables, "
             f"{r['iterations']} iterations, {r['seconds'] / 60:.1f} min.", "",
             "| | surface error mean | max | strain min .. max | all inside |", "|---|---|---|---|---|"]
    rows = [("before (today's mechanism, actuation optimized)", "before"), ("after (layout + actuation)", "after")]
    if "bound" in s:
        rows.append(("attachments moved freely (any layout's limit)", "bound"))
    for label, key in rows:
        v = s[key]
        lines.append(f"| {label} | {v['surface_mean_m'] * mm:.2f} mm | {v['surface_max_m'] * mm:.2f} mm | "
                     f"{(v['strain_min'] or 0):+.1%} .. {(v['strain_max'] or 0):+.1%} | "
                     f"{v['all_inside_strain_range']} |")
    g = s["goal"]
    lines += ["", f"Goal mean <= {g['mean_m'] * mm:.1f} mm: {'met' if g['mean_met'] else 'NOT met'}; "
              f"max <= {g['max_m'] * mm:.0f} mm: {'met' if g['max_met'] else 'NOT met'}; every pose inside the "
              f"strain range: {'yes' if g['strain_met'] else 'NO'}.", "",
              "| target | the target's own strain | before mean / max (mm) | after mean / max (mm) | strain after | "
              "actuators at a limit |", "|---|---|---|---|---|---|"]
    for t in r["per_target"]:
        b, a = t["before"], t["after"]
        ts = t.get("target_strain")
        own = f"{ts[0]:+.1%} .. {ts[1]:+.1%}" + ("" if t["target_inside_strain_range"] else " (outside)") if ts else "-"
        lines.append(f"| {t['target']} | {own} | {b['surface_mean_m'] * mm:.2f} / {b['surface_max_m'] * mm:.2f} | "
                     f"{a['surface_mean_m'] * mm:.2f} / {a['surface_max_m'] * mm:.2f} | "
                     f"{a.get('strain_min', 0):+.1%} .. {a.get('strain_max', 0):+.1%} | "
                     f"{', '.join(t['actuators_at_limit_after']) or '-'} |")
    lines += ["", "## Design parameters that moved (largest relative to their limit first)", ""]
    for p in r["moved_parameters"][:25]:
        key = next(k for k in ("move", "tilt", "change") if k in p)
        lines.append(f"- `{p['item']}.{p['what']}`: {key} {p[key]:.2f} {p['unit']} (limit {p['limit']:.1f} "
                     f"{p['unit']}){' **at the limit**' if p['at_limit'] else ''}")
    if len(r["moved_parameters"]) > 25:
        lines.append(f"- ... {len(r['moved_parameters']) - 25} more in report.json")
    cut: dict[str, int] = {}
    for entry in r["log"]:
        for loop in entry.get("loops_cut", {}):
            cut[loop] = cut.get(loop, 0) + 1
    if cut:
        lines += ["", "Design steps cut where a linkage loop would not assemble over its motors' range (that loop's "
                  "part of the step only; iterations with a cut, of " + f"{len(r['log'])}): "
                  + "; ".join(f"{loop} ({n})" for loop, n in sorted(cut.items(), key=lambda kv: -kv[1])) + "."]
    lines += ["", "## Binding envelope limits", ""]
    if not r["binding_limits"]:
        lines.append("No design variable ends at its envelope limit.")
    for b in r["binding_limits"][:12]:
        lines.append(f"- `{b['item']}.{b['what']}` at {b['now']:.2f} of {b['limit']:.2f} {b['unit']}: lifted, the "
                     f"model moves it to {b['would_move_to']:.2f} {b['unit']} ({b['beyond_limit_by']:+.2f} past the "
                     f"limit), objective gain {b['predicted_objective_gain']:.4g}")
    lines += _rings_markdown(r.get("attachment_rings"))
    lines += _bound_markdown(r)
    un = [t for t in r["per_target"] if not t["reached"]]
    if un:
        lines += ["", "## Targets out of reach", ""]
    for t in un:
        why = "; ".join(f"`{b['item']}.{b['what']}` ({b['beyond_limit_by']:+.2f} {b['unit']} past its limit: RMS "
                        f"{b['rms_now_mm']:.2f} -> {b['rms_released_mm']:.2f} mm)" for b in t.get("binding", []))
        if t.get("target_inside_strain_range") is False:
            why = ("the target itself lies outside the validated strain range (guard measure "
                   f"{t['target_strain'][0]:+.1%} .. {t['target_strain'][1]:+.1%}): no pose inside the range matches "
                   "it exactly, whatever the mechanism" + (f"; also {why}" if why else ""))
        if not t.get("binding"):
            why += ("; " if why else "") + "no envelope limit binds for it"
        if "bound" in t:
            bd = t["bound"]
            why += (f"; with its attachment sets moved freely it gets to {bd['surface_mean_m'] * mm:.2f} / "
                    f"{bd['surface_max_m'] * mm:.2f} mm mean / max: "
                    + ("reachable in principle, so the mechanism's structure or envelope limits it" if
                       t["bound_reaches_goal"] else "out of reach of any layout with these attachment sets"))
        wv = t["after"]["worst_vertex"]
        why = (f"largest vertex error {t['after']['vertex_max_m'] * mm:.1f} mm in region {wv['region']} (the target "
               f"moves that vertex {wv['target_moves_it_m'] * mm:.1f} mm), {t['after']['vertices_over_4mm']} of "
               f"{t['after']['vertices']} outer vertices more than 4 mm off; ") + why
        lines.append(f"- {t['target']}: {why}")
    if r.get("head_folder"):
        h = r["head_folder"]
        lines += ["", f"Head folder: `{h['head']}` (mechanism file vs design {h['file_vs_design_max_mm']:.2g} mm, "
                  f"link map (degree {h['map_degree']}) vs mechanism {h['map_vs_mechanism_max_mm']:.3f} mm"
                  + ("" if h["map_within_tolerance"] else f", MORE than the {h['map_tolerance_mm']} mm the runtime "
                     "needs") + ")."]
    lines += ["", "![before](pictures/mechanism_before.png)", "![after](pictures/mechanism_after.png)", ""]
    return "\n".join(lines)


def _link_changes(lp: LayoutProblem, p_after: np.ndarray, p_free: np.ndarray) -> list[dict[str, Any]]:
    """How far each link's free motion is from the layout's motion at the same target: its attachment set's
    centroid (mm) and its rotation (deg), largest first. What a mechanism would have to do differently."""
    from scipy.spatial.transform import Rotation

    from .attachment_bound import FreeAttachments

    free = FreeAttachments(lp.face)
    Ta, Tb = lp.boundary.transforms(p_after), free.transforms(p_free)
    out = []
    for link, c in zip(free.links, free.centers, strict=True):
        a = Ta.get(link, np.eye(4))
        b = Tb[link]
        shift = (b[:3, :3] @ c + b[:3, 3]) - (a[:3, :3] @ c + a[:3, 3])
        turn = Rotation.from_matrix(b[:3, :3] @ a[:3, :3].T).magnitude()
        out.append({"link": link, "centroid_mm": float(np.linalg.norm(shift) * 1e3),
                    "centroid_shift_mm": (shift * 1e3).tolist(), "rotation_deg": float(np.degrees(turn))})
    return sorted(out, key=lambda r: -r["centroid_mm"])


def _bound_markdown(r: Mapping[str, Any]) -> list[str]:
    """The attachments' own reach: per target the layout's result against the free attachment motions'."""
    if "bound" not in r["summary"]:
        return []
    mm = 1e3
    lines = ["", "## The attachments' own reach (any layout)", "", r["summary"]["bound"]["note"], "",
             "| target | after mean / max (mm) | attachments free mean / max (mm) | strain, free | goal reachable | "
             "links moved most differently from the layout (centroid mm, rotation deg) |",
             "|---|---|---|---|---|---|"]
    for t in r["per_target"]:
        a, b = t["after"], t["bound"]
        moved = ", ".join(f"{c['link']} {c['centroid_mm']:.1f} mm / {c['rotation_deg']:.1f}°"
                          for c in t["bound_link_changes"][:3])
        lines.append(f"| {t['target']} | {a['surface_mean_m'] * mm:.2f} / {a['surface_max_m'] * mm:.2f} | "
                     f"{b['surface_mean_m'] * mm:.2f} / {b['surface_max_m'] * mm:.2f} | "
                     f"{b.get('strain_min', 0):+.1%} .. {b.get('strain_max', 0):+.1%} | "
                     f"{'yes' if t['bound_reaches_goal'] else 'no'} | {moved} |")
    return lines


def _rings_markdown(rings: Mapping[str, Any] | None) -> list[str]:
    """The attachment-ring step's section: per set the rings changed and its nodes before/after, the rounds."""
    if not rings:
        return []
    lines = ["", "## Attachment rings", "",
             f"Ring step: a change kept when it lowers the objective by at least {rings['settings']['tol']:.0e} "
             f"(relative), at most {rings['settings']['max_rounds']} rounds; {len(rings['rounds'])} round(s) run.", "",
             "| node set (link) | rings | limit | nodes before | nodes after |", "|---|---|---|---|---|"]
    for row in rings["sets"]:
        lines.append(f"| {row['node_set']} ({row['link']}) | {row['rings']:+d} | {row['limit']} | "
                     f"{row['nodes_before']} | {row['nodes_after']} |")
    lines.append("")
    for i, rd in enumerate(rings["rounds"], 1):
        scr = [x for x in rd["screened"] if x["objective"] is not None]
        best = min(scr, key=lambda x: x["objective"]) if scr else None
        applied = ", ".join(f"{a['node_set']} {a['step']:+d}" for a in rd["applied"]) or "none"
        lines.append(f"- round {i}: {len(rd['screened'])} changes screened at objective {rd['objective_before']:.5g}"
                     + (f" (best single: {best['node_set']} {best['step']:+d}, {best['relative_change']:+.2%})"
                        if best else "") + f"; applied {applied}, objective {rd['objective_after']:.5g}")
    return lines
