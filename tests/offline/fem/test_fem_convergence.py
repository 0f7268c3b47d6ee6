"""Discretisation convergence on a non-homogeneous problem: a cantilever sagging under its own weight."""

from __future__ import annotations

import functools

import numpy as np

from offline.fem import SolverOptions, box_mesh, fixed, neo_hookean, solve_static

MAT = neo_hookean(2.0e4, 2.0e5)
LENGTH, THICK = 0.03, 0.01


@functools.cache
def tip_deflection(n: int, order: int) -> float:
    """Mean vertical displacement of the free end of a clamped 3:1:1 beam with (3n, n, n) hex cells."""
    mesh = box_mesh((LENGTH, THICK, THICK), (3 * n, n, n), order=order)
    res = solve_static(mesh, MAT, fixed(mesh, "x0"), options=SolverOptions(gravity=(0.0, 0.0, -9.81)))
    assert res.converged
    tip = mesh.node_sets["x1"]
    return float(np.mean(res.x[tip, 2] - np.asarray(mesh.nodes)[tip, 2]))


def test_error_decreases_with_mesh_refinement() -> None:
    ref = tip_deflection(4, 2)  # finest solution
    lin = [abs(tip_deflection(n, 1) - ref) for n in (1, 2, 4)]
    quad = [abs(tip_deflection(n, 2) - ref) for n in (1, 2)]
    assert lin[0] > lin[1] > lin[2] > 0
    assert lin[1] / lin[2] > 1.3
    assert quad[0] > quad[1] > 0
    assert quad[0] / quad[1] > 2.0  # higher rate for quadratic elements


def test_quadratic_tets_beat_linear_tets_in_bending() -> None:
    ref = tip_deflection(4, 2)
    # linear tets lock: far too stiff on coarse meshes
    assert abs(tip_deflection(1, 1)) < 0.3 * abs(ref)
    # 63 quadratic nodes are more accurate than 325 linear nodes
    assert abs(tip_deflection(1, 2) - ref) < 0.5 * abs(tip_deflection(4, 1) - ref)
    assert abs(tip_deflection(2, 2) - ref) < 0.05 * abs(ref)
