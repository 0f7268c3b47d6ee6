"""Name the parts of the skin tet mesh: outer/inner surfaces, link attachment patches, the skull, face units.

fTetWild remeshes the surface, so each boundary triangle of the tet mesh is classified by its distance to the
shell's outer and inner input surfaces and its normal. Link patches are inner-surface nodes that a link's face
units move by at least a fraction of their peak; overlaps go to the link with the larger relative motion. The
skull is the inner surface that no face unit moves noticeably, kept a clearance away from every link patch.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from offline.mesh.surface import closest_points, triangle_normals

#: Face units driving each link of the sample head: terms of (summed ARKit units, side filter: +1 = x > 0 only
#: (the face's left), -1 = x < 0 only, 0 = both). A node's activation for a link is its best term's motion
#: divided by that term's peak motion over the face.
LINK_UNITS: dict[str, tuple[tuple[tuple[str, ...], int], ...]] = {
    "jaw": ((("jawOpen",), 0),),
    "lip_corner_l": ((("mouthSmileLeft", "mouthStretchLeft"), 0),),
    "lip_corner_r": ((("mouthSmileRight", "mouthStretchRight"), 0),),
    "upper_lip": ((("mouthUpperUpLeft", "mouthUpperUpRight"), 0),),
    "lower_lip": ((("mouthLowerDownLeft", "mouthLowerDownRight"), 0),),
    "cheek_l": ((("cheekSquintLeft",), 0),),
    "cheek_r": ((("cheekSquintRight",), 0),),
    "brow_l": ((("browOuterUpLeft",), 0), (("browInnerUp",), +1)),
    "brow_r": ((("browOuterUpRight",), 0), (("browInnerUp",), -1)),
    "lid_l": ((("eyeBlinkLeft",), 0),),
    "lid_r": ((("eyeBlinkRight",), 0),),
}
SKULL = "skull"
#: Where link patches overlap, the node goes to the link listed first here (specific before broad: the lower
#: lip keeps its patch inside the jaw's, lids and brows are never taken by the cheeks).
LINK_PRIORITY = ("lid_l", "lid_r", "brow_l", "brow_r", "lower_lip", "upper_lip", "lip_corner_l", "lip_corner_r",
                 "cheek_l", "cheek_r", "jaw")


@dataclass(frozen=True)
class RegionParams:
    """Thresholds: link patch = activation >= ``link_fraction``; skull = peak motion of every face unit below
    ``skull_max_motion`` (m) and at least ``skull_clearance`` (m) from every link patch; ``surface_tol`` (m) is
    how far a boundary triangle may sit from the input surface and still belong to it. Overlapping patches are
    resolved by ``priority`` (first listed wins; links not listed come after, in mapping order), and a link loses
    the nodes closer than ``link_gap`` (m) to a link before it, so free skin separates patches that move apart.
    The gap must exceed the element size (the coarse preset's edges average 6.5 mm): with a 4 mm gap about 150
    tets had nodes on two patches that move relative to each other (jaw or lower lip against a lip corner moves
    16 mm across 5.6 mm of skin at 10 degrees of jaw), which no solver can follow; 10 mm leaves free skin between."""

    link_fraction: float = 0.5
    link_gap: float = 0.010
    priority: tuple[str, ...] = LINK_PRIORITY
    skull_max_motion: float = 0.0015
    skull_clearance: float = 0.008
    surface_tol: float = 0.0008
    links: Mapping[str, tuple[tuple[tuple[str, ...], int], ...]] = field(default_factory=lambda: dict(LINK_UNITS))


@dataclass(frozen=True)
class Surfaces:
    """Boundary of the tet mesh split by origin: outer (skin surface) and inner (attachment side) triangles and
    their sorted node indices."""

    outer_triangles: np.ndarray
    inner_triangles: np.ndarray
    wall_triangles: np.ndarray
    outer_nodes: np.ndarray
    inner_nodes: np.ndarray


def classify_boundary(nodes: np.ndarray, faces: np.ndarray, outer_v: np.ndarray, outer_t: np.ndarray,
                      inner_v: np.ndarray, inner_t: np.ndarray, tol: float) -> Surfaces:
    """Split outward boundary triangles into outer / inner / wall by distance and normal agreement.

    ``outer_t`` and ``inner_t`` are both oriented like the face (normals pointing out of the head).
    """
    cent = nodes[faces].mean(axis=1)
    fn = triangle_normals(nodes, faces)
    used = np.unique(faces)
    labels = np.full(len(faces), 2, dtype=np.int8)
    for lab, (v, t, sign) in enumerate(((outer_v, outer_t, 1.0), (inner_v, inner_t, -1.0))):
        tri, _, dist = closest_points(v, t, cent)
        agree = np.einsum("ij,ij->i", fn, triangle_normals(v, t)[tri]) * sign
        _, _, node_dist = closest_points(v, t, nodes[used])
        near = np.zeros(len(nodes), dtype=bool)
        near[used] = node_dist <= tol
        on_surface = (dist <= tol) & near[faces].all(axis=1)  # every corner on it, not just the centroid
        labels[on_surface & (agree > 0.5) & (labels == 2)] = lab
    outer, inner, wall = faces[labels == 0], faces[labels == 1], faces[labels == 2]
    return Surfaces(outer_triangles=outer, inner_triangles=inner, wall_triangles=wall,
                    outer_nodes=np.unique(outer), inner_nodes=np.unique(inner))


def interpolate(vertices: np.ndarray, triangles: np.ndarray, values: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Values (V, ...) given at surface vertices, interpolated at the closest surface point of each query point."""
    tri, bary, _ = closest_points(vertices, triangles, points)
    corner = values[triangles[tri]]  # (P, 3, ...)
    return np.einsum("pk,pk...->p...", bary, corner)


def link_activations(unit_offsets: Mapping[str, np.ndarray], positions: np.ndarray,
                     links: Mapping[str, tuple[tuple[tuple[str, ...], int], ...]]) -> dict[str, np.ndarray]:
    """Relative motion (0..1) of each surface vertex for each link, from the per-vertex unit offsets (m)."""
    out = {}
    for link, terms in links.items():
        best = np.zeros(len(positions))
        for names, side in terms:
            missing = [n for n in names if n not in unit_offsets]
            if missing:
                raise KeyError(f"link {link!r}: unknown face units {missing}")
            motion = np.linalg.norm(sum(unit_offsets[n] for n in names), axis=1)
            act = motion / max(float(motion.max()), 1e-300)
            if side:
                act = np.where(np.sign(positions[:, 0]) == side, act, 0.0)
            best = np.maximum(best, act)
        out[link] = best
    return out


def node_sets(nodes: np.ndarray, surfaces: Surfaces, inner_v: np.ndarray, inner_t: np.ndarray,
              vertex_units: Mapping[str, np.ndarray], params: RegionParams) -> dict[str, np.ndarray]:
    """Disjoint node sets on the inner surface: ``skull`` and one per link (sorted int64 node indices).

    ``vertex_units`` are the face-unit offsets (m) at the inner input surface's vertices.
    """
    act_v = link_activations(vertex_units, inner_v, params.links)
    names = list(params.links)
    stack_v = np.stack([act_v[n] for n in names], axis=1)
    peak_v = np.max(np.stack([np.linalg.norm(u, axis=1) for u in vertex_units.values()], axis=1), axis=1)
    inner = surfaces.inner_nodes
    pts = nodes[inner]
    act = interpolate(inner_v, inner_t, stack_v, pts)
    peak = interpolate(inner_v, inner_t, peak_v, pts)
    rank = [names.index(n) for n in params.priority if n in names]
    rank += [k for k in range(len(names)) if k not in rank]
    above = act[:, rank] >= params.link_fraction
    chosen = above.any(axis=1)
    winner = np.asarray(rank)[above.argmax(axis=1)]  # first link in priority order above the threshold
    sets: dict[str, np.ndarray] = {}
    taken = np.zeros(0, dtype=np.int64)
    for k in rank:
        idx = inner[chosen & (winner == k)]
        if len(taken) and len(idx) and params.link_gap > 0:
            dist, _ = cKDTree(nodes[taken]).query(nodes[idx])
            idx = idx[dist >= params.link_gap]
        sets[names[k]] = np.sort(idx).astype(np.int64)
        taken = np.concatenate([taken, idx])
    linked = inner[chosen]
    free = inner[~chosen & (peak < params.skull_max_motion)]
    if len(linked) and len(free):
        dist, _ = cKDTree(nodes[linked]).query(nodes[free])
        free = free[dist >= params.skull_clearance]
    sets[SKULL] = np.sort(free).astype(np.int64)
    return {SKULL: sets[SKULL], **{n: sets[n] for n in names}}
