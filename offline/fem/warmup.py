"""Compile the FEM's numba kernels into numba's on-disk cache once (``python -m offline.fem.warmup``).

The kernels are compiled on first use and cached beside their modules. A fresh checkout would otherwise pay that
compilation (about a minute and a half on two cores) inside the first FEM call, in every process that makes one
before the cache exists; ``make install`` runs this once instead. Every kernel is reached through the public API on
a tiny box, for both element orders, projected and plain tangents, and the rest-shape derivatives.
"""

from __future__ import annotations

import time

import numpy as np

from .energy import element_min_jacobian, gravity_forces, internal_forces, nodal_masses, stiffness, total_energy
from .materials import neo_hookean
from .mesh import box_mesh
from .rest_shape import mixed_stiffness, rest_energy_gradient
from .solve import Dirichlet, SolverOptions, solve_static


def warm(order: int) -> None:
    """Run every FEM kernel once on a two-element-wide box of element ``order``."""
    mesh = box_mesh((0.01, 0.01, 0.01), (2, 2, 2), order=order)
    mat = neo_hookean(1e4, 1e5)
    X = np.asarray(mesh.nodes)
    x = X + 1e-4 * np.sin(np.arange(X.size, dtype=float)).reshape(X.shape)
    total_energy(mesh, mat, x)
    internal_forces(mesh, mat, x)
    stiffness(mesh, mat, x)
    stiffness(mesh, mat, x, project_psd=True)
    element_min_jacobian(mesh, x)
    gravity_forces(mesh, mat, (0.0, 0.0, -9.81))
    nodal_masses(mesh, mat)
    rest_energy_gradient(mesh, mat, x)
    mixed_stiffness(mesh, mat, x)
    bottom, top = mesh.node_sets["z0"], mesh.node_sets["z1"]
    fixed = np.concatenate([bottom, top])
    target = np.concatenate([X[bottom], X[top] + [0.0, 0.0, -5e-4]])
    solve_static(mesh, mat, Dirichlet(fixed, target), options=SolverOptions(backend="superlu"))


def main() -> int:
    """Warm both element orders; prints how long it took."""
    start = time.perf_counter()
    for order in (1, 2):
        warm(order)
    print(f"FEM kernels compiled into numba's cache in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
