"""Turn the outer face surface into a closed skin shell of a given thickness.

The inner surface is the outer one moved inward along vertex normals smoothed over the surface (so the offset does
not fold at creases); where it still intersects itself (eyelid and mouth-corner rims), the positions of the inner
vertices involved, plus a few rings around them, are smoothed until no triangle crosses another. Each boundary loop
is closed by a side wall joining the outer loop to its inner copy, giving a watertight, outward-oriented surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from offline.mesh.surface import (
    adjacency,
    closed_manifold_problems,
    enclosed_volume,
    euler_characteristic,
    grow,
    self_intersections,
    smooth,
    vertex_normals,
)

OUTER, INNER, WALL = 0, 1, 2


class ShellError(RuntimeError):
    """The skin shell could not be made watertight and free of self-intersections."""


@dataclass(frozen=True)
class ShellParams:
    """Offset settings: skin thickness (m), normal smoothing passes, and the self-intersection repair
    (rings grown around the offending vertices, smoothing passes per round, maximum rounds)."""

    thickness: float = 0.006
    normal_smoothing: int = 40
    repair_rings: int = 3
    repair_passes: int = 10
    max_repair_rounds: int = 30


@dataclass(frozen=True)
class Shell:
    """A closed skin shell: vertices ``[outer (n); inner (n)]`` (inner vertex i + n lies under outer vertex i),
    outward triangles, a label per triangle (OUTER, INNER, WALL), and what the repair did."""

    vertices: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray
    n_outer: int
    repaired_vertices: int
    repair_rounds: int

    @property
    def volume(self) -> float:
        """Enclosed volume (m^3)."""
        return enclosed_volume(self.vertices, self.triangles)

    @property
    def inner_vertices(self) -> np.ndarray:
        """The inner surface's vertex positions (n, 3)."""
        return self.vertices[self.n_outer:]

    @property
    def inner_triangles(self) -> np.ndarray:
        """Inner-surface triangles indexed into :attr:`inner_vertices`, oriented like the outer surface."""
        return self.triangles[self.labels == INNER][:, ::-1] - self.n_outer


def offset_normals(vertices: np.ndarray, triangles: np.ndarray, passes: int) -> np.ndarray:
    """Unit vertex normals smoothed by ``passes`` rounds of neighbour averaging."""
    n = vertex_normals(vertices, triangles)
    adj = adjacency(triangles, len(vertices))
    n = smooth(n, adj, passes)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def stitch(outer_triangles: np.ndarray, loops: tuple[np.ndarray, ...], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed shell connectivity: outer triangles, reversed inner copies, and two wall triangles per rim edge."""
    inner = outer_triangles[:, ::-1] + n
    walls = []
    for loop in loops:
        a = loop
        b = np.roll(loop, -1)
        # the outer surface walks a -> b along its boundary; the wall walks b -> a on the outside
        walls.append(np.stack([b, a, a + n], axis=1))
        walls.append(np.stack([b, a + n, b + n], axis=1))
    wall = np.concatenate(walls) if walls else np.zeros((0, 3), dtype=np.int64)
    tris = np.concatenate([outer_triangles, inner, wall]).astype(np.int64)
    labels = np.concatenate([np.full(len(outer_triangles), OUTER), np.full(len(inner), INNER),
                             np.full(len(wall), WALL)]).astype(np.int8)
    return tris, labels


def build_shell(vertices: np.ndarray, triangles: np.ndarray, loops: tuple[np.ndarray, ...],
                params: ShellParams = ShellParams()) -> Shell:
    """Offset the outward-oriented surface inward by ``params.thickness`` and close it into a watertight shell."""
    n = len(vertices)
    normals = offset_normals(vertices, triangles, params.normal_smoothing)
    inner = vertices - params.thickness * normals
    tris, labels = stitch(triangles, loops, n)
    adj = adjacency(triangles, n)
    touched = np.zeros(n, dtype=bool)
    rounds = 0
    while True:
        allv = np.concatenate([vertices, inner])
        bad = self_intersections(allv, tris)
        if len(bad) == 0:
            break
        if rounds >= params.max_repair_rounds:
            raise ShellError(f"{len(bad)} shell triangles still intersect after {rounds} repair rounds; "
                             "try a smaller thickness or more normal smoothing")
        rounds += 1
        seeds = np.zeros(n, dtype=bool)
        seeds[np.unique(tris[bad]) % n] = True
        region = grow(adj, seeds, params.repair_rings)
        touched |= region
        inner = _smooth_offset(inner, adj, region, params.repair_passes)
    shell = Shell(vertices=np.concatenate([vertices, inner]), triangles=tris, labels=labels, n_outer=n,
                  repaired_vertices=int(touched.sum()), repair_rounds=rounds)
    check_shell(shell, n_loops=len(loops))
    return shell


def _smooth_offset(inner: np.ndarray, adj, region: np.ndarray, passes: int) -> np.ndarray:
    """Laplacian-smooth the inner positions inside ``region`` (the rest stays put), untangling local folds."""
    return smooth(inner, adj, passes, mask=region)


def check_shell(shell: Shell, n_loops: int) -> None:
    """Raise :class:`ShellError` unless the shell is a closed, consistently oriented, outward, non-self-intersecting
    surface of the genus expected from its boundary loops (a thickened disk with h holes has genus h)."""
    problems = closed_manifold_problems(shell.triangles)
    expected_chi = 2 - 2 * (n_loops - 1)
    chi = euler_characteristic(shell.triangles)
    if chi != expected_chi:
        problems.append(f"Euler characteristic {chi}, expected {expected_chi} for {n_loops} boundary loops")
    if shell.volume <= 0:
        problems.append(f"enclosed volume {shell.volume:.3e} m^3 is not positive (inward orientation)")
    bad = self_intersections(shell.vertices, shell.triangles)
    if len(bad):
        problems.append(f"{len(bad)} self-intersecting triangles")
    if problems:
        raise ShellError("skin shell invalid: " + "; ".join(problems))


def thickness_stats(shell: Shell) -> dict[str, float]:
    """Distance from each outer vertex to the inner surface: min, 1st percentile, median, max (metres)."""
    from offline.mesh.surface import closest_points

    inner_v = shell.vertices[shell.n_outer:]
    _, _, d = closest_points(inner_v, shell.inner_triangles, shell.vertices[: shell.n_outer])
    return {"min": float(d.min()), "p01": float(np.percentile(d, 1)), "median": float(np.median(d)),
            "max": float(d.max())}
