"""The FEM pose problem on a tiny box skin: m(p) → rigid link patches → Newton solve → stored outer surface."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

from models.headspec import load_head
from models.linkmap import LinkFit, LinkMap
from offline.dataset.fem_problem import FemSpec
from offline.dataset.generate import generate_dataset
from offline.dataset.store import PoseDataset, PoseStore
from offline.engine import SerialEngine
from offline.fem import box_mesh, save_mesh

HEAD = """
[head]
name = "box"
[buses.b]
driver = "dynamixel"
[[actuators]]
name = "lift_l"
bus = "b"
id = 1
unit = "mm"
min = 0.0
max = 1.5
max_velocity = 10.0
max_acceleration = 100.0
[[actuators]]
name = "lift_r"
bus = "b"
id = 2
unit = "mm"
min = -1.0
max = 1.0
max_velocity = 10.0
max_acceleration = 100.0
[links.skull]
rigid = true
[links.left]
actuators = ["lift_l"]
[links.right]
actuators = ["lift_r"]
"""


@pytest.fixture(scope="module")
def box_problem(tmp_path_factory):
    root = tmp_path_factory.mktemp("box")
    mesh = box_mesh((0.04, 0.02, 0.006), (8, 4, 2))
    X = np.asarray(mesh.nodes)
    z0 = np.asarray(mesh.node_sets["z0"])
    left = z0[X[z0, 0] < 0.0101]
    right = z0[X[z0, 0] > 0.0299]
    skull = z0[(X[z0, 0] > 0.0149) & (X[z0, 0] < 0.0251)]
    mesh = mesh.with_node_sets(skull=skull, left=left, right=right, outer=mesh.node_sets["z1"])
    save_mesh(root / "skin.vtu", mesh)
    (root / "head.toml").write_text(HEAD)
    head = load_head(root / "head.toml")

    def lift(name, acts, centroid):
        coef = np.zeros((3, 6))  # features [1, x, x²] of the link's one actuator
        coef[0, :3] = centroid
        coef[1, 2] = 0.001  # x = p / 1 mm → z moves by p
        return LinkFit(name, acts, coef, np.eye(3))

    links = {
        "skull": LinkFit("skull", (), np.zeros((1, 6)), np.eye(3), rigid=True),
        "left": lift("left", ("lift_l",), X[left].mean(0)),
        "right": lift("right", ("lift_r",), X[right].mean(0)),
    }
    LinkMap(head.actuator_names, [0.0, 0.0], [0.001, 0.001], links, head="box").save(root / "linkmap.json")
    spec = FemSpec(config=str(root / "head.toml"), mesh=str(root), linkmap=str(root / "linkmap.json"),
                   backend="superlu")
    return root, head, spec, mesh


def test_fem_pose_problem_moves_patches_and_stores_outer_surface(box_problem, tmp_path):
    _root, head, spec, mesh = box_problem
    prob = spec.build()
    assert len(prob.outer) == len(mesh.node_sets["z1"]) and len(prob.faces()) == 2 * 8 * 4
    samples = np.array([[0.0005, 0.0], [0.001, -0.0005], [0.0015, 0.001], [0.0012, 0.0008]])
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    summary = generate_dataset(tmp_path / "ds", spec, samples, head="box", names=head.actuator_names,
                               units=["m", "m"], lo=lo, hi=hi, engine=SerialEngine(), seed=0, sampling={},
                               progress_stream=None)
    assert summary["complete"] and summary["not_converged"] == 0
    ds = PoseDataset(tmp_path / "ds")
    X = np.asarray(mesh.nodes)
    top = X[prob.outer]
    above_left = top[:, 0] < 0.005
    above_right = top[:, 0] > 0.035
    for i, (pl, pr) in enumerate(samples):
        dz = ds.offsets[i][:, 2]
        # The skin over each lifted patch follows it (a 6 mm layer transmits most of the lift).
        assert np.all(np.sign(dz[above_left]) == np.sign(pl))
        assert 0.3 * pl < dz[above_left].mean() < 1.05 * pl
        if pr != 0:
            assert np.sign(dz[above_right].mean()) == np.sign(pr)
    # The stored pose is the FEM equilibrium of that pose's boundary conditions.
    from offline.fem import internal_forces

    rec = PoseStore(tmp_path / "ds").read_pose(2, with_state=True)
    bc = prob.dirichlet(samples[2])
    np.testing.assert_allclose(rec.state[bc.nodes], bc.positions, atol=1e-12)
    f = internal_forces(mesh, prob.material, rec.state)
    free = np.ones(mesh.n_nodes, dtype=bool)
    free[bc.nodes] = False
    scale = np.abs(f[~free]).max()
    assert np.abs(f[free]).max() < 1e-5 * scale
    # Warm starts from the nearest solved pose need no more Newton iterations than a cold start.
    cold = prob.solve(samples[3], None)
    assert PoseStore(tmp_path / "ds").read_pose(3).iterations <= cold.iterations
    np.testing.assert_allclose(ds.offsets[3] + ds.base_vertices, cold.surface, atol=1e-7)


def test_fem_spec_names_missing_node_sets(box_problem, tmp_path):
    _root, _head, spec, mesh = box_problem
    from models.errors import SpecError

    sets = {k: v for k, v in mesh.node_sets.items() if k != "right"}
    from offline.fem import TetMesh

    save_mesh(tmp_path / "skin.vtu", TetMesh(mesh.nodes, mesh.tets, sets))
    with pytest.raises(SpecError, match="node set right"):
        FemSpec(config=spec.config, mesh=str(tmp_path), linkmap=spec.linkmap).build()
    with pytest.raises(SpecError, match="mesh not found"):
        FemSpec(config=spec.config, mesh=str(tmp_path / "nothing"), linkmap=spec.linkmap).build()
    (tmp_path / "empty").mkdir()
    with pytest.raises(SpecError, match=r"no skin\.vtu"):
        FemSpec(config=spec.config, mesh=str(tmp_path / "empty"), linkmap=spec.linkmap).build()
    assert Path(spec.mesh).is_dir()
