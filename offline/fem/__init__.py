"""Skin FEM: hyperelastic tet meshes solved for quasi-static equilibrium.

- :mod:`offline.fem.mesh`: :class:`TetMesh` (frozen), structured generators, quadratic conversion, quality, I/O.
- :mod:`offline.fem.materials`: compressible neo-Hookean, Mooney-Rivlin and Yeoh models (isochoric split).
- :mod:`offline.fem.energy`: numba kernels for energy, internal forces and the CSR tangent stiffness.
- :mod:`offline.fem.linsolve`: CHOLMOD / PARDISO / SuperLU factorizations reusable for adjoint solves.
- :mod:`offline.fem.solve`: Dirichlet conditions and the load-stepped Newton solver :func:`solve_static`.
- :mod:`offline.fem.newton`: one load step of it (Newton iterations, directions, line search).
- :mod:`offline.fem.rest_shape`: derivatives with respect to the rest positions (∂W/∂X, ∂f/∂X) for design.
- :mod:`offline.fem.closed_form`: analytic reference answers (homogeneous uniaxial stretch).
"""

from .closed_form import uniaxial_neo_hookean
from .energy import (
    deformation_gradients,
    element_min_jacobian,
    gravity_forces,
    internal_forces,
    kernel_threads,
    min_jacobian,
    nodal_masses,
    prepare,
    stiffness,
    total_energy,
)
from .linsolve import Factorization, NotPositiveDefinite, SparseSolver, available_backends, factorize, make_solver
from .materials import (
    E_nu_from_mu_kappa,
    Material,
    energy_density,
    first_piola,
    mooney_rivlin,
    mu_kappa_from_E_nu,
    neo_hookean,
    neo_hookean_from_E_nu,
    yeoh,
)
from .mesh import TetMesh, boundary_faces, box_mesh, cylinder_mesh, load_mesh, save_mesh, tet_quality, to_quadratic
from .rest_shape import mixed_stiffness, rest_energy_gradient
from .solve import (
    Dirichlet,
    FactorCache,
    NotConverged,
    SolverOptions,
    StaticResult,
    combine,
    fixed,
    rigid_transform_dirichlet,
    solve_static,
    tangent_factorization,
)

__all__ = [
    "Dirichlet",
    "E_nu_from_mu_kappa",
    "FactorCache",
    "Factorization",
    "Material",
    "NotConverged",
    "NotPositiveDefinite",
    "SolverOptions",
    "SparseSolver",
    "StaticResult",
    "TetMesh",
    "available_backends",
    "boundary_faces",
    "box_mesh",
    "combine",
    "cylinder_mesh",
    "deformation_gradients",
    "element_min_jacobian",
    "energy_density",
    "factorize",
    "first_piola",
    "fixed",
    "gravity_forces",
    "internal_forces",
    "kernel_threads",
    "load_mesh",
    "make_solver",
    "min_jacobian",
    "mixed_stiffness",
    "mooney_rivlin",
    "mu_kappa_from_E_nu",
    "neo_hookean",
    "neo_hookean_from_E_nu",
    "nodal_masses",
    "prepare",
    "rest_energy_gradient",
    "rigid_transform_dirichlet",
    "save_mesh",
    "solve_static",
    "stiffness",
    "tangent_factorization",
    "tet_quality",
    "to_quadratic",
    "total_energy",
    "uniaxial_neo_hookean",
    "yeoh",
]
