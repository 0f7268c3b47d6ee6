"""The skin-strain guard judged against the FEM (what ``likeness offline guard`` runs): the attachment footprint,
the performances' poses solved into a FEM pose dataset, the guard's agreement with the FEM measure, the measure on a
refined skin, and a small test sample of pose datasets. Every report records the command that made it (``command``)
and the hashes of its inputs."""

from __future__ import annotations

import io
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from models.errors import ConfigError, UsageError
from models.headspec import HeadSpec
from models.strain_guard import StrainGuard
from offline.strain_eval import file_hash


def load_surface(mesh_dir: Path) -> tuple[Any, np.ndarray]:
    """The skin mesh of ``mesh_dir`` and its outer-surface triangles."""
    from offline.fem import load_mesh

    if not (mesh_dir / "skin.vtu").is_file() or not (mesh_dir / "face_units.npz").is_file():
        raise ConfigError(f"{mesh_dir}: needs skin.vtu and face_units.npz (likeness offline mesh)")
    mesh = load_mesh(mesh_dir / "skin.vtu")
    with np.load(mesh_dir / "face_units.npz") as z:
        triangles = np.asarray(z["surface_triangles"], dtype=np.int64)
    return mesh, triangles


def write_footprint(head: HeadSpec, mesh_dir: Path, out: str, command: str) -> tuple[np.ndarray, list[str]]:
    """Write each outer-surface triangle's distance to the rigid attachments to ``out``; returns the distances and
    the attachment node sets."""
    from models.strain_guard import save_footprint
    from offline.strain_eval import attachment_distance

    mesh, triangles = load_surface(mesh_dir)
    rim, sets = attachment_distance(head, mesh, triangles)
    save_footprint(out, rim, sets, {
        "command": command, "mesh_sha256": file_hash(mesh_dir / "skin.vtu"),
        "surface_sha256": file_hash(mesh_dir / "face_units.npz"),
        "rule": "centroid distance to boundary triangles/edges with all nodes in one attachment set"})
    return rim, sets


def solve_performances(head: HeadSpec, config: str, mesh: str, clips: Sequence[str], every_s: float, out: str,
                       workers: int = 1, backend: str = "auto", element_order: int = 1,
                       reuse: str | None = None) -> dict[str, Any]:
    """Sample the clips' poses every ``every_s`` seconds and solve the distinct ones with the FEM dataset tools
    into the (resumable) dataset folder ``out``; returns the dataset's summary. ``reuse``: an earlier such folder
    of the same skin problem, whose solved poses at the same values are copied instead of solved."""
    from offline.dataset.fem_problem import FemSpec, material_fields
    from offline.dataset.generate import generate_dataset
    from offline.engine import make_engine
    from offline.strain_eval import performance_poses

    poses, labels = performance_poses(head, clips, every_s=every_s)
    _, idx = np.unique(np.round(poses, 9), axis=0, return_index=True)
    idx = np.sort(idx)
    poses = poses[idx]
    spec = FemSpec(config=str(config), mesh=str(mesh), linkmap=str(head.path("linkmap")),
                   backend=backend, element_order=element_order, **material_fields(head.skin_material()))
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    units = ["rad" if a.kind == "rotary" else "m" for a in head.actuators]
    with make_engine("local", workers, 1) as engine:
        return generate_dataset(out, spec, poses, head=head.name, names=head.actuator_names, units=units,
                                lo=lo, hi=hi, engine=engine, seed=0,
                                sampling={"performances": [str(c) for c in clips], "every_s": every_s,
                                          "labels": [labels[i] for i in idx]},
                                rest_pose=head.neutral_pose, reuse=reuse)


def agreement(head: HeadSpec, config: str, datasets: Sequence[str | Path], fresh: int, command: str,
              names: Sequence[str] | None = None) -> dict[str, Any]:
    """The guard (full and reduced) against the FEM measure on pose datasets (folders, named by ``names`` where
    given), for the head's reference and the other one, and (``fresh`` > 0) the in-cycle check against the full
    measure on fresh seeded poses."""
    from offline.strain_eval import agreement_report, reduced_agreement

    if fresh < 0:
        raise UsageError(f"--fresh must be zero or positive, got {fresh}")
    t0 = time.perf_counter()
    guard = StrainGuard.for_head(head)
    if guard is None:
        raise ConfigError(f"{config}: the head names no existing predictor")
    fp = head.path("skin_guard")
    report = agreement_report(guard, datasets, names)
    other = "neutral" if guard.reference_kind == "rest" else "rest"
    alt = StrainGuard(guard.predictor, guard.neutral, guard.strain_range, guard.surface.rim_distance,
                      guard.surface.radius, guard.surface.band, samples=200, names=guard.names, reference=other)
    alt_report = agreement_report(alt, datasets, names)
    report["reference_comparison"] = {
        ref: {"guard_vs_fem": rep["guard_vs_fem"],
              "median_abs_error_vs_fem": {k: d["median_abs_error_vs_fem"] for k, d in rep["per_dataset"].items()}}
        for ref, rep in ((guard.reference_kind, report), (other, alt_report))}
    if fresh:
        report["reduced_vs_full_fresh"] = [reduced_agreement(guard, head, fresh, 1001, 1.0),
                                           reduced_agreement(guard, head, fresh, 1002, 0.25)]
    cal = guard.calibration
    report.update({
        "command": command,
        "inputs": {"config": {"path": str(head.source), "sha256": file_hash(head.source)},
                   "predictor": {"path": str(guard.predictor.path), "sha256": file_hash(guard.predictor.path)},
                   "skin_guard": {"path": str(fp), "sha256": file_hash(fp)} if fp is not None else None},
        "settings": {"strain_range": list(guard.strain_range), "radius_m": guard.surface.radius,
                     "band_m": guard.surface.band, "reference": guard.reference_kind,
                     "kept_area_fraction": guard.surface.kept_area_fraction},
        "reduced": {"patches": cal.patches, "patches_total": cal.patches_total, "vertices": cal.vertices,
                    "calibration_samples": cal.samples, "calibration_seed": cal.seed,
                    "calibration_agreement": cal.agreement},
        "seconds": time.perf_counter() - t0,
    })
    return report


def refinement(head: HeadSpec, mesh: str, dataset: str, poses: int, backend: str, command: str) -> dict[str, Any]:
    """The strain measure on the coarse skin and on its 1:8 refinement for ``poses`` poses of ``dataset`` spread
    over the guard's measure."""
    from offline.dataset.store import PoseDataset
    from offline.strain_eval import refinement_study

    guard = StrainGuard.for_head(head)
    ds = PoseDataset(dataset)
    idx = ds.usable
    full = guard.full_batch(ds.actuators[idx]) if guard is not None else np.zeros((len(idx), 2))
    order = idx[np.argsort(full[:, 1])]
    pick = order[np.linspace(0, len(order) - 1, poses).round().astype(int)]
    t0 = time.perf_counter()
    radius = guard.surface.radius if guard is not None else 0.008
    band = guard.surface.band if guard is not None else 0.005
    report = refinement_study(head, mesh, ds.actuators[pick], radius, band, backend=backend)
    report.update({"command": command, "dataset": str(dataset), "dataset_indices": [int(i) for i in pick],
                   "mesh_sha256": file_hash(Path(mesh) / "skin.vtu"), "seconds": time.perf_counter() - t0})
    return report


def write_json(path: str | Path, doc: dict[str, Any]) -> None:
    """Write a report as indented JSON, atomically, creating its folder."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_bytes(Path(path), (json.dumps(doc, indent=1) + "\n").encode())


def write_sample(path: str, datasets: Sequence[str | Path], per_dataset: int, command: str,
                 names: Sequence[str] | None = None) -> None:
    """Evenly spaced converged poses of each dataset: p, surface offsets (float32), base surface, faces; each pose
    labelled by its dataset's name (``names``, default the folder's) and index."""
    from offline.dataset.store import PoseDataset

    P, off, src = [], [], []
    base = faces = None
    labels = [str(r) for r in datasets] if names is None else [str(n) for n in names]
    for root, label in zip(datasets, labels, strict=True):
        ds = PoseDataset(root)
        idx = ds.usable
        pick = idx[np.linspace(0, len(idx) - 1, min(per_dataset, len(idx))).round().astype(int)]
        P.append(ds.actuators[pick])
        off.append(np.asarray(ds.offsets[pick], dtype=np.float32))
        src += [f"{Path(label).name}#{i}" for i in pick]
        base, faces = ds.base_vertices, ds.faces
    buf = io.BytesIO()
    np.savez_compressed(buf, p=np.concatenate(P), offsets=np.concatenate(off), base=base, faces=faces,
                        source=np.array(src), command=np.array(command))
    write_bytes(Path(path), buf.getvalue())
