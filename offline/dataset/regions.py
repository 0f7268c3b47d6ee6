"""Surface regions of a skin for per-region errors: each outer-surface vertex named after the node set under it.

Attachment patches and the skull are node sets on the inner surface; an outer vertex belongs to the set with the
nearest node, if that node lies within ``radius`` (about the skin thickness plus an element), and to ``free``
(skin between attachments) otherwise. Regions describe where an error sits; they play no part in training.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

FREE = "free"
#: Default reach (m) from an outer vertex to its region's node set: the sample skin is about 6 mm thick.
DEFAULT_RADIUS = 0.008


def label_surface(points: np.ndarray, nodes: np.ndarray, node_sets: Mapping[str, np.ndarray],
                  radius: float = DEFAULT_RADIUS, exclude: tuple[str, ...] = ("outer", "outer_surface", "surface"),
                  ) -> tuple[tuple[str, ...], np.ndarray]:
    """Region names and the region index (V,) of every point; names are the node sets used, then ``free``."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    names = [n for n in node_sets if n not in exclude and len(node_sets[n])]
    if not names:
        return (FREE,), np.zeros(len(pts), dtype=np.int32)
    owner = np.concatenate([np.full(len(node_sets[n]), k) for k, n in enumerate(names)])
    idx = np.concatenate([np.asarray(node_sets[n], dtype=np.int64) for n in names])
    dist, near = cKDTree(np.asarray(nodes, dtype=np.float64)[idx]).query(pts)
    labels = np.where(dist <= radius, owner[near], len(names)).astype(np.int32)
    return (*names, FREE), labels


def single_region(n_vertices: int, name: str = "surface") -> tuple[tuple[str, ...], np.ndarray]:
    """Every vertex in one region (problems without node sets)."""
    return (name,), np.zeros(n_vertices, dtype=np.int32)
