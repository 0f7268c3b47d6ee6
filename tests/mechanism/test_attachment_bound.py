"""The attachments' own reach (:mod:`offline.design.attachment_bound`): the free rigid motions contain every layout's
attachment motion, and the bound started from a mechanism's solution ends no worse than it."""

from __future__ import annotations

import numpy as np
import pytest

from offline.design.attachment_bound import FreeAttachments, attachment_bound, bound_problem
from tests.mechanism._builders import sample_layout


@pytest.fixture(scope="module")
def layout():
    lp = sample_layout({"jawOpen": 0.6, "mouthSmileLeft": 0.5})
    space = lp.space
    lp.boundary.set_design(space.project(np.random.default_rng(5).normal(size=space.size) * space.scale * 0.1))
    head = lp.face.skin.head
    p = np.array(head.neutral_pose, dtype=float)
    for name, deg in (("jaw", 10.0), ("lip_corner_l_up", 15.0), ("lip_corner_l_back", 10.0)):
        p[head.actuator_names.index(name)] = np.radians(deg)
    return lp, p


def test_coordinates_invert_the_free_motions(layout) -> None:
    lp, _ = layout
    free = FreeAttachments(lp.face)
    rng = np.random.default_rng(0)
    p = np.concatenate([np.r_[rng.uniform(-1.0, 1.0, 3), rng.uniform(-0.02, 0.02, 3)] for _ in free.links])
    T = free.transforms(p)
    assert np.allclose(free.coordinates(T), p, atol=1e-12)
    # a rotation turns the set about its own rest centroid: the centroid moves by the translation alone
    for i, link in enumerate(free.links):
        c = free.centers[i]
        assert np.allclose(T[link][:3, :3] @ c + T[link][:3, 3], c + p[6 * i + 3:6 * i + 6], atol=1e-12)
    rest = free(np.zeros(free.size))  # zero coordinates: every set where the skin was made
    assert np.allclose(rest.dof_values, np.asarray(lp.face.mesh.nodes).ravel()[rest.dofs], atol=1e-15)

def test_every_layout_motion_is_a_free_motion(layout) -> None:
    """The redesigned mechanism's attachment motion at a pose, read as free coordinates, is the same Dirichlet
    condition node for node: the free motions contain every layout's."""
    lp, p = layout
    free = FreeAttachments(lp.face)
    T = lp.boundary.transforms(p)
    q = free.coordinates({n: T[n] for n in free.links if n in T})
    a, b = lp.boundary(p), free(q)
    assert np.array_equal(a.dofs, b.dofs)
    assert np.abs(a.dof_values - b.dof_values).max() < 1e-12
    assert np.abs(a.dof_values - np.asarray(lp.face.mesh.nodes).ravel()[a.dofs]).max() > 1e-3  # the pose moves


@pytest.mark.slow
def test_the_bound_started_from_a_layout_solution_is_no_worse(layout) -> None:
    """A target actuated on the mechanism, then its attachments freed: the objective does not rise and the match
    falls (the free motions have more room than the linkage), with the pose inside the strain range."""
    from offline.design.actuation import optimize_targets

    lp, _ = layout
    mech = optimize_targets(lp.problem, lp.targets, max_iterations=8, tol_value=1e-3)[0]
    problem, free = bound_problem(lp.face)
    T = lp.boundary.transforms(mech.p)
    res = attachment_bound(problem, free, lp.targets, starts=[({n: T[n] for n in free.links if n in T}, mech.x)],
                           weights=[mech.strain_weight], iterations=8, progress=lambda _: None)[0]
    assert res.value <= mech.value * (1 + 1e-9)
    assert res.match < 0.9 * mech.match
    assert res.strain_inside
