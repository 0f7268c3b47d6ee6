"""Checks of the skin-strain guard against the FEM: footprint, performance poses, agreement, mesh refinement.

- :func:`attachment_distance`: each outer-surface triangle's distance to the rigid attachment regions.
- :func:`performance_poses`: actuator poses a head's sample performances command (``arkit.*`` channels through the
  hidden-space inverse, without the guard, at the daemon's rate).
- :func:`agreement_report`: the guard's decisions (full and reduced) against the same measure computed on FEM
  surfaces of pose datasets (``likeness offline dataset`` folders).
- :func:`refine_uniform`: split every tet into eight (edge midpoints), for the measure's refinement study.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models.headspec import HeadSpec
from models.strain_guard import StrainGuard, SurfaceStrain


def file_hash(path: str | Path) -> str:
    """SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def attachment_sets(head: HeadSpec, mesh: Any, skull_set: str = "skull") -> dict[str, np.ndarray]:
    """Node sets of the mesh that hold the skin rigidly: the skull and every link's attachment set."""
    sets = {skull_set: np.asarray(mesh.node_sets[skull_set])} if skull_set in mesh.node_sets else {}
    for link in head.links:
        if link.node_set in mesh.node_sets:
            sets[link.node_set] = np.asarray(mesh.node_sets[link.node_set])
    return sets


def attachment_distance(head: HeadSpec, mesh: Any, triangles: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """Distance (T,) from each surface triangle's centroid (``triangles`` in mesh numbering) to the nearest rigid
    attachment region: the boundary triangles and boundary edges whose nodes all lie in one attachment node set.

    The regions are geometric (a refined mesh covers the same ones), so the distance does not depend on the mesh.
    """
    from offline.fem import boundary_faces
    from offline.mesh.surface import closest_points

    nodes = np.asarray(mesh.nodes)
    bf = boundary_faces(mesh)
    tris, edges = [], []
    sets = attachment_sets(head, mesh)
    for idx in sets.values():
        member = np.zeros(mesh.n_nodes, dtype=bool)
        member[idx] = True
        tris.append(bf[member[bf].all(axis=1)])
        e = np.sort(bf[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edges.append(np.unique(e[member[e].all(axis=1)], axis=0))
    centroids = nodes[np.asarray(triangles)].mean(axis=1)
    d = np.full(len(centroids), np.inf)
    t = np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)
    if len(t):
        d = np.minimum(d, closest_points(nodes, t, centroids)[2])
    e = np.concatenate(edges) if edges else np.zeros((0, 2), dtype=np.int64)
    if len(e):
        d = np.minimum(d, _segment_distance(centroids, nodes[e[:, 0]], nodes[e[:, 1]]))
    return d, {k: len(v) for k, v in sets.items()}


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray, candidates: int = 16) -> np.ndarray:
    """Distance from each point to the nearest of the segments a–b (candidates: nearest by midpoint)."""
    from scipy.spatial import cKDTree

    k = min(candidates, len(a))
    _, cand = cKDTree(0.5 * (a + b)).query(points, k=k)
    cand = np.asarray(cand).reshape(len(points), k)
    pa, ab = points[:, None, :] - a[cand], b[cand] - a[cand]
    t = np.clip(np.einsum("pki,pki->pk", pa, ab) / np.maximum(np.einsum("pki,pki->pk", ab, ab), 1e-30), 0.0, 1.0)
    return np.linalg.norm(pa - t[..., None] * ab, axis=2).min(axis=1)


def performance_poses(head: HeadSpec, files: Sequence[str | Path], every_s: float = 0.1, rate_hz: float = 500.0
                      ) -> tuple[np.ndarray, list[str]]:
    """Actuator poses (N, A) SI sampled every ``every_s`` from performance clips, with labels ``file@t``.

    Actuator channels convert from config units; ``arkit.*`` channels are solved frame by frame at ``rate_hz``
    with the head's skin solver settings, without the strain guard (the guard is what gets judged).
    """
    from models.clip import load_clip_file
    from models.skin_targets import PREFIX, skin_targets_for_head

    targets = skin_targets_for_head(head)
    names = head.actuator_names
    neutral = np.array(head.neutral_pose)
    poses, labels = [], []
    for f in files:
        clip = load_clip_file(f)
        p_prev = neutral.copy()
        n = math.floor(clip.duration * rate_hz) + 1
        stride = max(1, round(every_s * rate_hz))
        for i in range(n):
            t = i / rate_hz
            values = clip.sample(t)
            arkit = {k: v for k, v in values.items() if k.startswith(PREFIX)}
            p = neutral.copy()
            if arkit and targets is not None:
                p = targets.inverse.solve(targets.weights(arkit), p_prev=p_prev, max_iterations=targets.max_iterations,
                                          tol=targets.tol).p
                p_prev = p
            for j, name in enumerate(names):
                if name in values:
                    p[j] = head.actuators[j].from_config_units(values[name])
            if i % stride == 0:
                poses.append(np.clip(p, [a.min for a in head.actuators], [a.max for a in head.actuators]))
                labels.append(f"{Path(f).name}@{t:.2f}")
    return np.array(poses), labels


def _ok(m: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return (m[:, 0] >= lo) & (m[:, 1] <= hi)


def agreement_report(guard: StrainGuard, datasets: Iterable[str | Path],
                     names: Sequence[str] | None = None) -> dict[str, Any]:
    """Guard (full and reduced) vs the FEM measure on every converged pose of the given pose datasets, each keyed
    by its name in ``names`` (default its folder) and recorded with its content hash (a dataset and its pack
    agree)."""
    from offline.dataset.store import PoseDataset, PoseStore

    lo, hi = guard.strain_range
    per_set = {}
    all_fem, all_full, all_red = [], [], []
    roots = list(datasets)
    labels = [str(r) for r in roots] if names is None else [str(n) for n in names]
    if len(labels) != len(roots):
        raise ValueError(f"{len(labels)} names for {len(roots)} datasets")
    for root, label in zip(roots, labels, strict=True):
        PoseStore(root).consolidate()  # the poses solved so far (a run may still be adding to it)
        ds = PoseDataset(root)
        idx = ds.usable
        if not np.array_equal(ds.faces, guard.surface.faces):
            raise ValueError(f"{label}: the dataset's surface triangles differ from the predictor's")
        fem_surface = SurfaceStrain(ds.base_vertices, ds.faces, guard.surface.rim_distance, guard.surface.radius,
                                    guard.surface.band)
        P = ds.actuators[idx]
        fem = np.array([fem_surface.extremes(ds.base_vertices + np.asarray(ds.offsets[i], dtype=np.float64))
                        for i in idx]).reshape(-1, 2)
        full = guard.full_batch(P)
        red = np.array([guard.measure(p) for p in P]).reshape(-1, 2)
        ok_fem, ok_full, ok_red = _ok(fem, lo, hi), _ok(full, lo, hi), _ok(red, lo, hi)
        ok_chk = np.array([guard.check(p) for p in P], dtype=bool)
        per_set[label] = {
            "poses": len(idx), "fem_ok_fraction": float(ok_fem.mean()) if len(idx) else None,
            "guard_vs_fem": float((ok_full == ok_fem).mean()) if len(idx) else None,
            "reduced_vs_full": float((ok_red == ok_full).mean()) if len(idx) else None,
            "check_vs_full": float((ok_chk == ok_full).mean()) if len(idx) else None,
            "guard_accepts_fem_refuses": int((ok_full & ~ok_fem).sum()),
            "guard_refuses_fem_accepts": int((~ok_full & ok_fem).sum()),
            "max_abs_error_vs_fem": {"min": float(np.abs(full[:, 0] - fem[:, 0]).max()) if len(idx) else None,
                                     "max": float(np.abs(full[:, 1] - fem[:, 1]).max()) if len(idx) else None},
            "median_abs_error_vs_fem": {"min": float(np.median(np.abs(full[:, 0] - fem[:, 0]))) if len(idx) else None,
                                        "max": float(np.median(np.abs(full[:, 1] - fem[:, 1]))) if len(idx) else None},
            "dataset_hash": ds.content_hash(),
        }
        all_fem.append(fem)
        all_full.append(full)
        all_red.append(red)
    fem, full, red = (np.concatenate(a) if a else np.zeros((0, 2)) for a in (all_fem, all_full, all_red))
    n = len(fem)
    ok_fem, ok_full, ok_red = _ok(fem, lo, hi), _ok(full, lo, hi), _ok(red, lo, hi)
    return {
        "poses": int(n),
        "guard_vs_fem": float((ok_full == ok_fem).mean()) if n else None,
        "reduced_vs_full": float((ok_red == ok_full).mean()) if n else None,
        "reduced_vs_fem": float((ok_red == ok_fem).mean()) if n else None,
        "fem_ok_fraction": float(ok_fem.mean()) if n else None,
        "per_dataset": per_set,
    }


def reduced_agreement(guard: StrainGuard, head: HeadSpec, n: int, seed: int, range_fraction: float = 1.0,
                      boundary_prob: float = 0.15) -> dict[str, Any]:
    """The in-cycle check (``guard.check``) against the full measure on ``n`` fresh seeded poses of the head's
    sampler (no FEM needed: both read the predictor), over ``range_fraction`` of each range around neutral."""
    from offline.dataset.sampling import sample_poses

    P = sample_poses(head, n, seed=seed, boundary_prob=boundary_prob, range_fraction=range_fraction)
    lo, hi = guard.strain_range
    ok_full = _ok(guard.full_batch(P), lo, hi)
    ok_chk = np.array([guard.check(p) for p in P], dtype=bool)
    return {"poses": int(n), "seed": int(seed), "range_fraction": float(range_fraction),
            "boundary_prob": float(boundary_prob), "full_ok_fraction": float(ok_full.mean()),
            "check_vs_full": float((ok_chk == ok_full).mean()),
            "check_accepts_full_refuses": int((ok_chk & ~ok_full).sum()),
            "check_refuses_full_accepts": int((~ok_chk & ok_full).sum())}


def refine_uniform(mesh: Any, outer: np.ndarray, triangles: np.ndarray) -> tuple[Any, np.ndarray, np.ndarray]:
    """Split every linear tet into 8 (mid-edge nodes; the same geometry, half the edge length).

    Returns the refined mesh (node sets keep mid-edge nodes of edges inside the set), its outer-surface node
    indices (the old ones first, in order) and the outer triangles split 1 → 4, in refined node numbering.
    """
    from offline.fem import TetMesh, to_quadratic
    from offline.fem.mesh import signed_volumes

    q = to_quadratic(mesh)
    t = np.asarray(q.tets)
    # 10-node order: corners 0-3, then mid-edges of (0,1) (1,2) (0,2) (0,3) (1,3) (2,3).
    c0, c1, c2, c3, m01, m12, m02, m03, m13, m23 = (t[:, i] for i in range(10))
    tets = np.concatenate([
        np.stack([c0, m01, m02, m03], 1), np.stack([m01, c1, m12, m13], 1),
        np.stack([m02, m12, c2, m23], 1), np.stack([m03, m13, m23, c3], 1),
        np.stack([m01, m02, m03, m13], 1), np.stack([m01, m02, m12, m13], 1),
        np.stack([m02, m03, m13, m23], 1), np.stack([m02, m12, m13, m23], 1),
    ])
    nodes = np.asarray(q.nodes)
    neg = signed_volumes(nodes, tets) < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    fine = TetMesh(nodes, tets, dict(q.node_sets))
    # Mid-edge node of each (sorted) edge, from the quadratic tets.
    from offline.fem.mesh import QUADRATIC_EDGES

    pairs = np.sort(np.asarray(mesh.tets)[:, QUADRATIC_EDGES].reshape(-1, 2), axis=1)
    mids = t[:, 4:].reshape(-1)
    key = pairs[:, 0] * mesh.n_nodes + pairs[:, 1]
    lookup = dict(zip(key.tolist(), mids.tolist(), strict=True))

    def mid(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        lo_, hi_ = np.minimum(a, b), np.maximum(a, b)
        return np.array([lookup[k] for k in (lo_ * mesh.n_nodes + hi_).tolist()], dtype=np.int64)

    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
    tris = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                           np.stack([ab, bc, ca], 1)])
    new_outer = np.setdiff1d(np.unique(tris), outer)
    return fine, np.concatenate([outer, new_outer]), tris


def refinement_study(head: HeadSpec, mesh_dir: str | Path, poses: np.ndarray, radius: float, band: float,
                     backend: str = "auto") -> dict[str, Any]:
    """The measure and the single-triangle extreme on the coarse skin and on its 1:8 refinement, per pose."""
    import tempfile
    import time

    from offline.dataset.fem_problem import FemSpec
    from offline.fem import load_mesh, save_mesh

    mesh_dir = Path(mesh_dir)
    coarse = load_mesh(mesh_dir / "skin.vtu")
    with np.load(mesh_dir / "face_units.npz") as z:
        outer = np.asarray(z["surface_nodes"], dtype=np.int64)
        tris = np.asarray(z["surface_triangles"], dtype=np.int64)
    fine, fine_outer, fine_tris = refine_uniform(coarse, outer, tris)
    linkmap = str(head.path("linkmap"))
    out: dict[str, Any] = {"coarse": {"tets": int(coarse.n_tets), "surface_triangles": len(tris)},
                           "fine": {"tets": int(fine.n_tets), "surface_triangles": len(fine_tris)},
                           "radius_m": radius, "band_m": band, "poses": []}
    with tempfile.TemporaryDirectory() as tmp:
        fdir = Path(tmp) / "fine"
        fdir.mkdir()
        save_mesh(fdir / "skin.vtu", fine)
        lookup = np.full(fine.n_nodes, -1)
        lookup[fine_outer] = np.arange(len(fine_outer))
        np.savez(fdir / "face_units.npz", surface_nodes=fine_outer, surface_triangles=fine_tris)
        problems = {}
        for name, folder in (("coarse", mesh_dir), ("fine", fdir)):
            spec = FemSpec(config=str(head.source), mesh=str(folder), linkmap=linkmap, backend=backend)
            prob = spec.build()
            # Both meshes must see the same link frames: use the coarse mesh's frame alignment for both.
            if name == "fine":
                prob.frame_offset = problems["coarse"][0].frame_offset
            nodes = np.asarray(prob.mesh.nodes)
            rim, _ = attachment_distance(head, prob.mesh, prob.outer[prob.faces()])
            surf = SurfaceStrain(nodes[prob.outer], prob.faces(), rim, radius, band)
            problems[name] = (prob, surf)
        for p in poses:
            row: dict[str, Any] = {"p": [float(x) for x in p]}
            for name, (prob, surf) in problems.items():
                t0 = time.perf_counter()
                sol = prob.solve(np.asarray(p, dtype=np.float64), None)
                eps = surf.triangle_strains(sol.surface)
                kept = surf.kept
                row[name] = {"converged": bool(sol.converged), "seconds": time.perf_counter() - t0,
                             "measure": list(surf.extremes(sol.surface)),
                             "single_triangle_all": [float(np.nanmin(eps[:, 0])), float(np.nanmax(eps[:, 1]))],
                             "single_triangle_kept": [float(np.nanmin(eps[kept, 0])), float(np.nanmax(eps[kept, 1]))],
                             "kept_area_fraction": surf.kept_area_fraction}
                if name == "fine":
                    # The fine solution at the coarse surface's vertices (the refinement keeps them first, in
                    # order), measured on the coarse triangles: separates the measure's own mesh dependence from
                    # the change of the FEM solution itself.
                    coarse_surf = problems["coarse"][1]
                    on_coarse = sol.surface[: len(coarse_surf.rest)]
                    row["fine_on_coarse_triangles"] = {"measure": list(coarse_surf.extremes(on_coarse))}
            out["poses"].append(row)
    return out
