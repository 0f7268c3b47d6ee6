"""FEM virtual uniaxial test: a specimen stretched or compressed between two grips, nominal strain vs axial force.

Specimens (:mod:`offline.material.specimen`): the strip is meshed with ``box_mesh`` (pull axis x), the cylinder
with ``cylinder_mesh`` (axis z). One grip face stays at axial coordinate 0, the other moves to (1 + ε)·L; the
nominal strain is the grip separation change over the gauge length L (the whole specimen between the grips) and
the axial force is the sum of the axial reaction forces on the moving grip.

Grips:

- ``frictionless`` (default): only the axial displacement of the grip faces is prescribed, the ends contract
  freely; rigid modes are removed by pinning one grip-face node and one axial-rotation DoF. The answer is
  homogeneous and equals the closed form of :mod:`offline.material.closed_form`.
- ``clamped``: the grip faces are fully fixed (no lateral motion), which stiffens the specimen.

Each strain step is warm-started from the previous solution, stretched affinely along the axis so that the grips
start exactly at their targets (every element keeps J > 0), and strain increments larger than ``max_increment``
are split into sub-steps. Strains are visited outward from zero (tension ascending, compression descending).

Every step is one :func:`offline.fem.solve_static` call; frictionless grips prescribe single coordinates through
``Dirichlet.components``.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numpy as np

from offline.material.models import MaterialParams
from offline.material.specimen import Specimen, SpecimenPlan

GRIPS: tuple[str, ...] = ("frictionless", "clamped")

SMALL_MESH_TETS = 20_000
"""Below this many tets the FEM kernels run single-threaded (threading overhead exceeds the work)."""


class VirtualTestError(RuntimeError):
    """The virtual test found no equilibrium at some strain (names specimen, grips and strain)."""


@dataclass(frozen=True)
class MeshSettings:
    """Mesh resolution of a virtual test: element ``order`` (1 or 2) and a density multiplier ``refine`` (>= 1).

    Defaults: frictionless grips give a homogeneous answer that any mesh reproduces exactly, so a coarse linear
    mesh suffices; clamped grips concentrate strain at the grips and use quadratic tets (linear tets lock at
    ν ≈ 0.47 and bend poorly).
    """

    order: int
    refine: int = 1

    def __post_init__(self) -> None:
        if self.order not in (1, 2):
            raise ValueError(f"element order must be 1 or 2, got {self.order!r}")
        if self.refine < 1:
            raise ValueError(f"mesh refinement must be >= 1, got {self.refine!r}")


def default_mesh_settings(grips: str) -> MeshSettings:
    """Default mesh for ``grips`` (see :class:`MeshSettings`)."""
    return MeshSettings(order=1 if grips == "frictionless" else 2)


def specimen_mesh(specimen: Specimen, settings: MeshSettings):
    """Tet mesh of ``specimen`` with node sets ``grip_fixed`` (axial 0) and ``grip_moving`` (axial L)."""
    from offline.fem import TetMesh, box_mesh, cylinder_mesh

    r = settings.refine
    if specimen.kind == "strip":
        L, W, T = specimen.length, specimen.width, specimen.thickness
        h = min(W, T)
        div = (max(2, math.ceil(L / h / 2)) * r, max(1, round(W / h)) * r, max(1, round(T / h)) * r)
        mesh = box_mesh((L, W, T), div, order=settings.order)
        return mesh.with_node_sets(grip_fixed=mesh.node_sets["x0"], grip_moving=mesh.node_sets["x1"]), 0
    radius = specimen.width / 2.0
    n_radial = 3 * r
    n_height = max(2, round(specimen.length / (radius / n_radial))) if settings.order == 1 else max(2, 2 * r)
    mesh = cylinder_mesh(radius, specimen.length, n_radial, n_height, order=settings.order)
    # The faceted rim cuts area off the disk (about 1 % at 3 radial cells): scale radially so that the mesh has the
    # specimen's true cross-section, and the axial force means the same as the closed form's stress times area.
    p = np.asarray(mesh.nodes)
    corners = p[np.asarray(mesh.tets)[:, :4]]
    volume = float(np.sum(np.abs(np.einsum("ij,ij->i", np.cross(corners[:, 1] - corners[:, 0],
                                                                 corners[:, 2] - corners[:, 0]),
                                           corners[:, 3] - corners[:, 0]))) / 6.0)
    scale = math.sqrt(specimen.area * specimen.length / volume)
    nodes = p * np.array([scale, scale, 1.0])
    mesh = TetMesh(nodes, mesh.tets, {"grip_fixed": mesh.node_sets["bottom"], "grip_moving": mesh.node_sets["top"]})
    return mesh, 2


@dataclass(frozen=True)
class _Setup:
    mesh: object
    axis: int
    length: float
    fixed_nodes: np.ndarray
    moving_nodes: np.ndarray
    mask: np.ndarray  # (N, 3) bool: constrained DoFs


def _setup(mesh, axis: int, length: float, grips: str) -> _Setup:
    X = np.asarray(mesh.nodes)
    fixed_nodes = np.asarray(mesh.node_sets["grip_fixed"])
    moving_nodes = np.asarray(mesh.node_sets["grip_moving"])
    mask = np.zeros(X.shape, dtype=bool)
    if grips == "clamped":
        mask[fixed_nodes] = True
        mask[moving_nodes] = True
        return _Setup(mesh, axis, length, fixed_nodes, moving_nodes, mask)
    mask[fixed_nodes, axis] = True
    mask[moving_nodes, axis] = True
    lat = [a for a in range(3) if a != axis]
    face = X[fixed_nodes]
    centre = face.mean(axis=0)
    # pin the fixed-face node nearest the face centre (no lateral translation) ...
    pin = fixed_nodes[np.argmin(np.linalg.norm(face - centre, axis=1))]
    mask[pin, :] = True
    # ... and stop the rotation about the axis: the node farthest from the pin along lat[0] keeps lat[1]
    d = face - X[pin]
    far = fixed_nodes[np.argmax(np.abs(d[:, lat[0]]) - 1e-6 * np.abs(d[:, lat[1]]))]
    mask[far, lat[1]] = True
    return _Setup(mesh, axis, length, fixed_nodes, moving_nodes, mask)


def _predict(x_prev: np.ndarray, setup: _Setup, eps_prev: float, eps: float) -> np.ndarray:
    """Warm start: the previous solution stretched affinely along the axis so the grips land on their targets."""
    x = x_prev.copy()
    x[:, setup.axis] = x_prev[:, setup.axis] * (1.0 + eps) / (1.0 + eps_prev)
    return x


def _backend() -> str:
    """Sparse backend for the small virtual-test meshes: CHOLMOD, else SuperLU.

    PARDISO is avoided: after it rejects an indefinite tangent (compression steps), the same solver object also
    rejects the PSD-projected one, so the Newton fallback cannot recover.
    """
    from offline.fem import available_backends

    return "cholmod" if "cholmod" in available_backends() else "superlu"


def _numba_threads_for(n_tets: int) -> contextlib.AbstractContextManager:
    """Run small meshes on one numba thread (larger ones keep the caller's count): on a busy 2-core machine the
    parallel kernels' thread barrier costs 10-20x the work itself for a few hundred tets."""
    from offline.fem import kernel_threads

    return kernel_threads(1) if n_tets < SMALL_MESH_TETS else contextlib.nullcontext()


def run_specimen(params: MaterialParams, specimen: Specimen, strains: np.ndarray, *, grips: str = "frictionless",
                 mesh_settings: MeshSettings | None = None, max_increment: float = 0.05,
                 tol: float = 1e-9) -> np.ndarray:
    """Axial forces (N) of the virtual test of ``specimen`` at each nominal strain (any order, strains > -1)."""
    from offline.fem import Dirichlet, SolverOptions, solve_static

    if grips not in GRIPS:
        raise ValueError(f"grips must be one of {', '.join(GRIPS)}, got {grips!r}")
    eps_all = np.asarray(strains, dtype=float)
    if np.any(~np.isfinite(eps_all)) or np.any(eps_all <= -0.9):
        raise ValueError("strains must be finite and above -0.9")
    settings = mesh_settings or default_mesh_settings(grips)
    mesh, axis = specimen_mesh(specimen, settings)
    setup = _setup(mesh, axis, specimen.length, grips)
    material = params.to_fem_material()
    X = np.asarray(mesh.nodes)
    forces = np.zeros(eps_all.shape)
    options = SolverOptions(backend=_backend(), tol_force=tol, max_iterations=40)

    nodes = np.flatnonzero(setup.mask.any(axis=1))
    components = setup.mask[nodes]

    moving_rows = np.flatnonzero(np.isin(nodes, setup.moving_nodes))

    def solve(x_guess: np.ndarray) -> tuple[np.ndarray, float]:
        """Equilibrium positions and the axial force: the summed axial reactions on the moving grip."""
        dirichlet = Dirichlet(nodes, x_guess[nodes], components)
        result = solve_static(mesh, material, dirichlet, x0=x_guess, options=options)
        return result.x, float(result.reactions[moving_rows, setup.axis].sum())

    with _numba_threads_for(mesh.n_tets):
        _sweep(eps_all, forces, X, mesh, material, setup, solve, specimen, grips, max_increment)
    return forces


def _sweep(eps_all, forces, X, mesh, material, setup, solve, specimen, grips, max_increment) -> None:
    """Visit the strains outward from zero on each branch, warm-starting every solve; fills ``forces``."""
    from offline.fem import NotConverged

    for branch in (np.flatnonzero(eps_all >= 0.0), np.flatnonzero(eps_all < 0.0)):
        if branch.size == 0:
            continue
        order = branch[np.argsort(np.abs(eps_all[branch]))]
        x, eps_prev, force = X.copy(), 0.0, 0.0
        for i in order:
            target = float(eps_all[i])
            start = eps_prev
            n_sub = max(1, math.ceil(abs(target - start) / max_increment - 1e-9))
            for k in range(1, n_sub + 1):
                eps_k = start + (target - start) * k / n_sub
                try:
                    x, force = solve(_predict(x, setup, eps_prev, eps_k))
                except NotConverged as exc:
                    hint = ""
                    if eps_k < 0.0 and specimen.kind == "strip":
                        hint = " (a slender strip buckles in compression: test compression on the cylinder)"
                    raise VirtualTestError(
                        f"{specimen.describe()}, {grips} grips: no equilibrium at strain {eps_k:.4g}{hint}: {exc}"
                    ) from exc
                eps_prev = eps_k
            forces[i] = force


def run_plan(params: MaterialParams, plan: SpecimenPlan, strains: np.ndarray, *, grips: str = "frictionless",
             mesh_settings: MeshSettings | None = None) -> np.ndarray:
    """Axial forces (N) at each strain, each strain tested on the specimen the plan assigns to it."""
    eps = np.asarray(strains, dtype=float)
    forces = np.zeros(eps.shape)
    for specimen, mask in plan.for_strains(eps):
        forces[mask] = run_specimen(params, specimen, eps[mask], grips=grips, mesh_settings=mesh_settings)
    return forces
