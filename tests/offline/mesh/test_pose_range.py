"""The shipped coarse skin solves across the sample head's whole actuator range through the shipped link map m(p).

Every actuator alone at its configured min and max, and seeded random combinations uniform over the full ranges,
must converge with the constrained nodes exactly on their rigid-link targets. The full sweep is ``slow``; a fast
subset (the jaw that used to fail, a lip at its limit, one random pose) runs in the default suite.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from models.linkmap import LinkMap
from offline.fem import (
    SolverOptions,
    load_mesh,
    neo_hookean_from_E_nu,
    rigid_transform_dirichlet,
    solve_static,
)

ROOT = Path(__file__).resolve().parents[3]
HEAD = ROOT / "heads" / "sample" / "head.toml"
SKIN = ROOT / "heads" / "sample" / "skin" / "skin.vtu"
N_RANDOM = 20


@pytest.fixture(scope="module")
def setup():
    head = load_head(HEAD)
    return head, LinkMap.for_head(head), load_mesh(SKIN)


def _single_poses(head) -> list[dict[str, float]]:
    out = []
    for name in head.actuator_names:
        spec = head.actuator(name)
        out += [{name: spec.min}, {name: spec.max}]
    return out


def _random_poses(head, n: int, seed: int = 0) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    return [{a: float(rng.uniform(head.actuator(a).min, head.actuator(a).max)) for a in head.actuator_names}
            for _ in range(n)]


def _solve_and_check(head, linkmap, mesh, values: dict[str, float]) -> None:
    transforms = linkmap.transforms(values)
    links = [k for k in mesh.node_sets if k != "skull"]
    bc = rigid_transform_dirichlet(mesh, {k: transforms.get(k, np.eye(4)) for k in links}, fixed_sets=["skull"])
    result = solve_static(mesh, neo_hookean_from_E_nu(78000.0, 0.47), bc, options=SolverOptions(load_steps="auto"))
    assert result.converged
    last = result.log[-1]
    assert last["residual"] <= last["tolerance"]
    assert np.array_equal(result.x[bc.nodes], bc.positions), "constrained nodes must sit exactly on their targets"
    from offline.fem.energy import min_jacobian

    assert min_jacobian(mesh, result.x) > 0
    moved = max(float(np.abs(T - np.eye(4)).max()) for T in transforms.values())
    assert moved > 1e-4  # the pose really moves a link


def _label(values: dict[str, float]) -> str:
    return ",".join(f"{k}={v:.3f}" for k, v in values.items()) if len(values) < 3 else "random"


FAST = [("jaw", 10.0), ("jaw", 15.0), ("lower_lip", 30.0)]


@pytest.mark.parametrize(("name", "deg"), FAST, ids=[f"{n}={d:g}" for n, d in FAST])
def test_fast_subset_converges_exactly_on_the_boundary(setup, name, deg) -> None:
    head, lm, mesh = setup
    _solve_and_check(head, lm, mesh, lm.from_config_units({name: deg}))


def test_one_random_full_range_pose_converges(setup) -> None:
    head, lm, mesh = setup
    _solve_and_check(head, lm, mesh, _random_poses(head, 1, seed=1)[0])


@pytest.mark.slow
@pytest.mark.parametrize("index", range(26))
def test_every_actuator_alone_at_min_and_max(setup, index) -> None:
    head, lm, mesh = setup
    poses = _single_poses(head)
    assert len(poses) == 2 * len(head.actuator_names) == 26
    _solve_and_check(head, lm, mesh, poses[index])


@pytest.mark.slow
@pytest.mark.parametrize("index", range(N_RANDOM))
def test_random_combinations_over_the_full_ranges(setup, index) -> None:
    head, lm, mesh = setup
    _solve_and_check(head, lm, mesh, _random_poses(head, N_RANDOM, seed=0)[index])
