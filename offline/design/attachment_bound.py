"""The attachments' own reach: each link's attachment node set moved by any rigid motion, with no mechanism.

Every layout a mechanism can take moves each attachment set rigidly; a free rigid motion per set and per target
(a rotation vector about the set's rest centroid and a translation, six numbers a link) is therefore a superset of
every layout, every envelope and every actuation. The best match of a target over these free motions, with every
pose inside the validated strain range, is a lower bound on the error any layout design can reach with these
attachment node sets and this skin: when the bound misses a goal, no envelope limit is what binds.

The free motions are an :class:`offline.design.actuation.ActuationSpace` (one "actuator" per coordinate), so the
bound is the clone's own actuation optimizer (match, strain constraint with its augmented-Lagrangian rounds) run on
that space, started from the layout's own solution where one is given.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from offline.fem.solve import Dirichlet, SolverOptions, rigid_transform_dirichlet

from .actuation import ActuationProblem, ActuationSpace, TargetResult, optimize_targets, strain_text
from .face import FaceSkin

#: Bounds of the free motion, per coordinate: far past any linkage's travel (a rotation vector component in rad,
#: a translation component in m), so they never bind on a face; they keep the optimizer's box finite.
ROTATION_LIMIT = np.pi / 2
TRANSLATION_LIMIT = 0.05


class FreeAttachments:
    """The Dirichlet conditions of a face skin whose attachment sets move freely (callable as an
    :class:`~offline.design.actuation.ActuationSpace` boundary): p holds, per moving link in the skin's order, a
    rotation vector (rad) about the set's rest centroid and a translation (m), in the mesh frame; the skull stays."""

    def __init__(self, face: FaceSkin) -> None:
        skin = face.skin
        self.mesh = skin.mesh
        self.links = tuple(skin.moving)
        self.sets = tuple(skin.moving[name] for name in self.links)
        X = np.asarray(self.mesh.nodes, dtype=np.float64)
        self.centers = np.array([X[np.asarray(self.mesh.node_sets[s])].mean(axis=0) for s in self.sets])
        self.skull = skin.spec.skull_set

    @property
    def size(self) -> int:
        return 6 * len(self.links)

    def names(self) -> tuple[str, ...]:
        """One name per coordinate of p (``LINK.rx`` .. ``LINK.tz``)."""
        return tuple(f"{link}.{c}" for link in self.links for c in ("rx", "ry", "rz", "tx", "ty", "tz"))

    def transforms(self, p: np.ndarray) -> dict[str, np.ndarray]:
        """Each link's rigid motion (4 × 4, mesh frame) at p."""
        p = np.asarray(p, dtype=np.float64).reshape(len(self.links), 6)
        out = {}
        for link, c, row in zip(self.links, self.centers, p, strict=True):
            T = np.eye(4)
            R = Rotation.from_rotvec(row[:3]).as_matrix()
            T[:3, :3] = R
            T[:3, 3] = c - R @ c + row[3:]
            out[link] = T
        return out

    def coordinates(self, transforms: Mapping[str, np.ndarray]) -> np.ndarray:
        """p of the given rigid motions (links not given stay at rest): the inverse of :meth:`transforms`."""
        p = np.zeros((len(self.links), 6))
        for i, (link, c) in enumerate(zip(self.links, self.centers, strict=True)):
            T = transforms.get(link)
            if T is None:
                continue
            R = np.asarray(T, dtype=np.float64)[:3, :3]
            p[i, :3] = Rotation.from_matrix(R).as_rotvec()
            p[i, 3:] = np.asarray(T)[:3, 3] - c + R @ c
        return p.ravel()

    def __call__(self, p: np.ndarray) -> Dirichlet:
        T = self.transforms(p)
        return rigid_transform_dirichlet(self.mesh, {s: T[link] for link, s in zip(self.links, self.sets,
                                                                                   strict=True)},
                                         fixed_sets=[self.skull])


def free_space(free: FreeAttachments, rotation_limit: float = ROTATION_LIMIT,
               translation_limit: float = TRANSLATION_LIMIT) -> ActuationSpace:
    """The free motions as an actuation space: every coordinate independent, at rest in the middle of its box."""
    per_link = np.array([rotation_limit] * 3 + [translation_limit] * 3)
    hi = np.tile(per_link, len(free.links))
    return ActuationSpace(free.names(), -hi, hi, np.zeros(free.size), free)


def bound_problem(face: FaceSkin, strain: bool = True, margin: float = 0.01,
                  tol_force: float = 1e-8) -> tuple[ActuationProblem, FreeAttachments]:
    """The actuation problem on the free motions (the layout design's solver settings and strain constraint)."""
    from .strain_constraint import face_strain_constraint

    free = FreeAttachments(face)
    opts = SolverOptions(backend=face.skin.spec.backend, tol_force=tol_force, max_iterations=60, load_steps=1)
    con = face_strain_constraint(face, margin=margin) if strain else None
    problem = ActuationProblem(face.mesh, face.skin.material, free_space(free), face.outer, solver=opts, strain=con)
    return problem, free


def attachment_bound(problem: ActuationProblem, free: FreeAttachments, targets: Sequence[np.ndarray],
                     starts: Sequence[tuple[Mapping[str, np.ndarray], np.ndarray | None] | None] | None = None,
                     weights: Sequence[float] | None = None, iterations: int = 100,
                     progress: Callable[[str], None] = print,
                     labels: Sequence[str] | None = None) -> list[TargetResult]:
    """Per target, the best free motions. ``starts[k]``: (link transforms, equilibrium or None) to start from, e.g. the
    layout's own solution, with its strain-penalty weight ``weights[k]``; the optimizer also tries the previous
    target's solution and rest, and keeps the best."""
    out: list[TargetResult] = []
    for k, target in enumerate(targets):
        t0 = time.perf_counter()
        previous = None
        if starts is not None and starts[k] is not None:
            transforms, x = starts[k]
            weight = problem.strain.weight if problem.strain is not None else 0.0
            if weights is not None:
                weight = max(weight, float(weights[k]))
            x0 = None if x is None else np.asarray(x, dtype=np.float64)
            previous = [TargetResult(free.coordinates(transforms), x0, np.inf, np.inf, 0, False, 0, [], 0.0,
                                     strain_weight=weight)]
        res = optimize_targets(problem, [target], previous=previous, max_iterations=iterations,
                               tol_value=1e-4)[0]
        name = labels[k] if labels is not None else str(k)
        strain = strain_text(res)
        progress(f"[bound] target {k + 1}/{len(targets)} {name}: {res.iterations} it from {res.start}, match "
                 f"{res.match:.4g}{strain} ({time.perf_counter() - t0:.0f}s)")
        out.append(res)
    return out
