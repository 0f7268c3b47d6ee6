"""Attachment node sets grown or shrunk by whole rings of surface triangles (the layout envelope's
``attachment_rings``).

A link grips the skin by a node set on the skin's inner surface. One ring outward is every surface vertex joined to
the set by a surface triangle and not already in it (nor in any other attachment set, the skull's included: no
node belongs to two sets); one ring inward is the set's own boundary vertices (those with a surface neighbour
outside the set). The surface is the tet mesh's boundary triangles whose three corners lie on the surface the sets
lie on (``surface_nodes``, the inner surface on a design face), so a ring never creeps round the skin's rim onto
the face. A shrink is never offered below ``min_nodes(n0)`` nodes (at least 6 and a third of the set's original
count) or when the nodes left are nearly collinear (second principal extent under 1 mm): the link's grip must stay
a patch that fixes the skin's position and rotation there.

Ring counts are relative to the head's own sets; the sets at given counts are rebuilt from the originals (shrinks
first, then growth one ring at a time, sets in name order), so a state is fully described by its counts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from offline.fem.mesh import TetMesh, boundary_faces

#: The smallest grip a shrink may leave (nodes), whatever the set's original size.
MIN_NODES = 6
#: A shrunk set must still span a patch: its second principal extent (RMS, m) at least this.
MIN_SPREAD_M = 1e-3


def min_nodes(n0: int) -> int:
    """The fewest nodes a set of ``n0`` nodes may be shrunk to: 6, or a third of the original if more."""
    return max(MIN_NODES, math.ceil(n0 / 3))


@dataclass(frozen=True)
class Candidate:
    """One discrete change: set ``name`` by ``step`` rings (+1 grow, −1 shrink) from ``rings``; nodes before and
    after, or ``why`` it is not allowed (then ``nodes_after`` is the count it would have had)."""

    name: str
    step: int
    rings: int
    nodes_before: int
    nodes_after: int
    why: str = ""

    @property
    def allowed(self) -> bool:
        return not self.why


class AttachmentRings:
    """The ring operations on a mesh's attachment node sets ``names`` (the others in ``fixed`` are never changed
    and never grown into)."""

    def __init__(self, mesh: TetMesh, names: Sequence[str], fixed: Sequence[str] = (),
                 surface_nodes: np.ndarray | None = None) -> None:
        if mesh.order != 1:
            raise ValueError("attachment rings need a linear tet mesh (rings are counted on corner nodes)")
        self.mesh = mesh
        self.names = tuple(sorted(names))
        self.fixed = tuple(fixed)
        self.original = {n: np.unique(np.asarray(mesh.node_sets[n], dtype=np.int64)) for n in self.names}
        faces = boundary_faces(mesh)
        if surface_nodes is not None:
            on = np.zeros(mesh.n_nodes, dtype=bool)
            on[np.asarray(surface_nodes, dtype=np.int64)] = True
            faces = faces[on[faces].all(axis=1)]
        self.faces = faces
        e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        n = mesh.n_nodes
        A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
        self.adjacency = ((A + A.T) > 0).astype(np.int8).tocsr()
        self._fixed_nodes = np.zeros(n, dtype=bool)
        for f in self.fixed:
            self._fixed_nodes[np.asarray(mesh.node_sets[f], dtype=np.int64)] = True

    def _member(self, idx: np.ndarray) -> np.ndarray:
        m = np.zeros(self.mesh.n_nodes, dtype=bool)
        m[idx] = True
        return m

    def ring_out(self, idx: np.ndarray, taken: np.ndarray) -> np.ndarray:
        """The surface vertices next to ``idx`` (by a surface triangle), not in it and not ``taken`` (a mask)."""
        member = self._member(idx)
        near = np.asarray(self.adjacency @ member.astype(np.int8)).ravel() > 0
        return np.flatnonzero(near & ~member & ~taken)

    def boundary(self, idx: np.ndarray) -> np.ndarray:
        """The set's own boundary ring: its vertices with a surface neighbour outside the set."""
        member = self._member(idx)
        outside = np.asarray(self.adjacency @ (~member).astype(np.int8)).ravel() > 0
        return np.flatnonzero(member & outside)

    def shrink_why(self, name: str, idx: np.ndarray) -> str:
        """Why the set ``idx`` (of ``name``) is not an allowed grip: too few nodes or collinear; "" when it is."""
        need = min_nodes(len(self.original[name]))
        if len(idx) < need:
            return f"{len(idx)} nodes, below the minimum grip of {need}"
        X = np.asarray(self.mesh.nodes)[idx]
        s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False) / math.sqrt(len(idx))
        if s[1] < MIN_SPREAD_M:
            return f"nodes nearly collinear ({s[1] * 1e3:.2f} mm across)"
        return ""

    def sets_at(self, rings: Mapping[str, int]) -> dict[str, np.ndarray]:
        """Every set at ``rings`` (name → whole rings, + grown, − shrunk; missing names 0), rebuilt from the
        originals; ValueError when a shrink goes below the minimum grip."""
        sets = {n: self.original[n].copy() for n in self.names}
        for n in self.names:
            for _ in range(max(-int(rings.get(n, 0)), 0)):
                sets[n] = np.setdiff1d(sets[n], self.boundary(sets[n]))
            if rings.get(n, 0) < 0 and (why := self.shrink_why(n, sets[n])):
                raise ValueError(f"attachment set {n!r} at {rings[n]} rings: {why}")
        for r in range(1, max([int(v) for v in rings.values()] + [0]) + 1):
            for n in self.names:
                if int(rings.get(n, 0)) >= r:
                    taken = self._fixed_nodes.copy()
                    for other, idx in sets.items():
                        if other != n:
                            taken[idx] = True
                    sets[n] = np.union1d(sets[n], self.ring_out(sets[n], taken))
        return sets

    def candidates(self, rings: Mapping[str, int], limits: Mapping[str, int]) -> list[Candidate]:
        """Each set's +1 and −1 ring change from ``rings`` within ``limits`` (name → the most rings either way),
        allowed or with why not."""
        now = self.sets_at(rings)
        out = []
        for n in self.names:
            r, lim = int(rings.get(n, 0)), int(limits.get(n, 0))
            for step in (+1, -1):
                new = r + step
                if abs(new) > lim:
                    out.append(Candidate(n, step, r, len(now[n]), len(now[n]),
                                         f"the envelope allows {lim} ring(s) either way"))
                    continue
                try:
                    after = self.sets_at({**rings, n: new})[n]
                except ValueError as exc:
                    out.append(Candidate(n, step, r, len(now[n]), 0, str(exc).split(": ", 1)[-1]))
                    continue
                why = "" if len(after) != len(now[n]) else "no surface vertex left to take"
                out.append(Candidate(n, step, r, len(now[n]), len(after), why))
        return out

    def mesh_at(self, rings: Mapping[str, int]) -> TetMesh:
        """The mesh with every set at ``rings`` (nodes and tets unchanged)."""
        return self.mesh.with_node_sets(**self.sets_at(rings))
