"""What a dataset was simulated on, for reports: its mesh, its material and its surface regions.

Datasets record these in the manifest (``mesh``, ``problem.material``) and ``base.npz`` (regions). Datasets
written before those records existed are described from the mesh file their manifest names, when it is still
there; otherwise the unknown fields are None and say so, rather than guessed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline.dataset.regions import single_region
from offline.dataset.store import PoseDataset


def _fem_problem(ds: PoseDataset):
    """The FEM problem the manifest names, rebuilt (paths as recorded), or None when it cannot be."""
    problem = ds.manifest.get("problem", {})
    if problem.get("kind") != "fem" or not all(problem.get(k) for k in ("config", "mesh", "linkmap")):
        return None
    from offline.dataset.fem_problem import FemSpec

    try:
        skin = FemSpec(config=problem["config"], mesh=problem["mesh"], linkmap=problem["linkmap"]).build()
    except Exception:
        return None
    return skin if len(skin.base_surface()) == len(ds.base_vertices) else None


def mesh_info(ds: PoseDataset) -> dict[str, Any]:
    """Element order, element count, node count and surface counts of the dataset's mesh."""
    if isinstance(ds.manifest.get("mesh"), dict):
        return dict(ds.manifest["mesh"])
    info: dict[str, Any] = {"kind": ds.manifest.get("problem", {}).get("kind", "unknown"), "element_order": None,
                            "n_elements": None, "n_nodes": None, "n_surface_vertices": len(ds.base_vertices),
                            "n_surface_triangles": len(ds.faces)}
    skin = _fem_problem(ds)
    if skin is None:
        info["note"] = "dataset records no mesh and the mesh its manifest names cannot be read here"
        return info
    return {**skin.mesh_info(), "note": "read from the mesh file named in the manifest (not recorded in the dataset)"}


def regions(ds: PoseDataset) -> tuple[tuple[str, ...], np.ndarray]:
    """Region names and region index (V,) of every surface vertex."""
    if ds.vertex_region is not None and ds.region_names:
        return ds.region_names, np.asarray(ds.vertex_region, dtype=np.int32)
    skin = _fem_problem(ds)
    if skin is not None:
        return skin.surface_regions()
    return single_region(len(ds.base_vertices))


def material_info(ds: PoseDataset) -> dict[str, Any]:
    """The skin material the dataset was simulated with, and where it came from."""
    problem = ds.manifest.get("problem", {})
    if problem.get("kind") == "fem":
        mat = dict(problem.get("material") or {})
        mat.setdefault("source", "not recorded (dataset predates material sources; FEM defaults of that version)")
        return mat
    return {"model": None, "source": f"{problem.get('kind', 'unknown')} problem: no material "
            "(analytic test surface)"}

