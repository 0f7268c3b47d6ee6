"""The FEM pose problem on a tiny box skin: m(p) → rigid link patches → Newton solve → stored outer surface."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

from models.errors import SpecError
from models.headspec import load_head
from offline.dataset.box import write_box_problem
from offline.dataset.fem_problem import FemSpec
from offline.dataset.generate import generate_dataset
from offline.dataset.store import PoseDataset, PoseStore
from offline.engine import SerialEngine
from offline.fem import save_mesh


@pytest.fixture(scope="module")
def box_problem(tmp_path_factory):
    root = tmp_path_factory.mktemp("box")
    spec = write_box_problem(root)
    head = load_head(root / "head.toml")
    return root, head, spec, spec.build().mesh


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
    # Surface regions (for per-region errors) name the patch under each outer vertex; the mesh is recorded.
    names = np.array(ds.region_names)[ds.vertex_region]
    assert set(names[above_left]) == {"left"} and set(names[above_right]) == {"right"}
    assert set(ds.region_names) == {"skull", "left", "right", "free"}
    assert ds.manifest["mesh"]["element_order"] == mesh.order and ds.manifest["mesh"]["n_elements"] == mesh.n_tets
    from offline.dataset.describe import mesh_info, regions

    (tmp_path / "ds" / "dataset.json").write_text(
        __import__("json").dumps({k: v for k, v in ds.manifest.items() if k != "mesh"}))
    old = PoseDataset(tmp_path / "ds")  # as a dataset written before mesh and region records: rebuilt from inputs
    old.vertex_region = None
    assert mesh_info(old)["n_elements"] == mesh.n_tets and "read from the mesh file" in mesh_info(old)["note"]
    assert regions(old)[0] == ds.region_names and np.array_equal(regions(old)[1], ds.vertex_region)
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


def test_mesh_folder_surface_and_face_units_from_face_units_npz(box_problem, tmp_path):
    """The layout written by `likeness offline mesh`: surface nodes/triangles and face units in face_units.npz."""
    _root, _head, spec, mesh = box_problem
    from offline.fem import boundary_faces

    save_mesh(tmp_path / "skin.vtu", mesh)
    top = np.asarray(mesh.node_sets["z1"])
    bf = boundary_faces(mesh)
    tris = bf[np.isin(bf, top).all(axis=1)]
    offsets = np.zeros((2, len(top), 3), dtype=np.float32)
    offsets[1, :, 2] = 0.001
    np.savez(tmp_path / "face_units.npz", names=np.array(["jawOpen", "browInnerUp"]), offsets=offsets,
             surface_nodes=top, surface_triangles=tris)
    prob = FemSpec(config=spec.config, mesh=str(tmp_path), linkmap=spec.linkmap).build()
    np.testing.assert_array_equal(prob.outer, top)
    assert prob.faces().shape == tris.shape and prob.faces().max() == len(top) - 1
    names, fu = prob.face_units()
    assert names == ("jawOpen", "browInnerUp") and fu.shape == (2, len(top), 3)
    np.savez(tmp_path / "face_units.npz", names=np.array(["x"]), offsets=np.zeros((1, 3, 3)), surface_nodes=top)
    with pytest.raises(SpecError, match="offsets"):
        FemSpec(config=spec.config, mesh=str(tmp_path), linkmap=spec.linkmap).build()


def test_head_material_reaches_the_fem_and_E_does_not_change_poses(box_problem):
    """Prescribed displacements only: the pose depends on nu (and shape parameters), not on E."""
    import dataclasses

    from models.material import SkinMaterial
    from offline.dataset.fem_problem import material_fields

    _root, _head, spec, _mesh = box_problem
    p = np.array([0.0012, -0.0006])
    soft = dataclasses.replace(spec, **material_fields(SkinMaterial("neo_hookean", 62_600.0, 0.47, source="a")))
    stiff = dataclasses.replace(soft, youngs_modulus=626_000.0)
    other_nu = dataclasses.replace(soft, poisson_ratio=0.40)
    mr = dataclasses.replace(spec, **material_fields(SkinMaterial("mooney_rivlin", 62_600.0, 0.47, {"c01": 9000.0},
                                                                  source="b")))
    assert soft.build().material.name == "neo_hookean" and mr.build().material.name == "mooney_rivlin"
    assert soft.describe()["material"]["source"] == "a" and soft.token != stiff.token
    a, b, c = (s.build().solve(p, None).surface for s in (soft, stiff, other_nu))
    np.testing.assert_allclose(a, b, atol=1e-9)
    assert np.abs(a - c).max() > 1e-6  # nu does move the skin


def test_quadratic_elements_keep_the_surface_and_stay_close_to_the_linear_solution(box_problem):
    """element_order=2 solves the same skin on 10-node tets: same outer vertices, same patch motion, and the
    answer moves towards the stiffer-in-bending linear one only by a fraction of the displacement."""
    from dataclasses import replace

    _root, _head, spec, mesh = box_problem
    lin = spec.build()
    quad = replace(spec, element_order=2).build()
    assert quad.mesh.order == 2 and quad.mesh.n_nodes > mesh.n_nodes
    assert np.array_equal(quad.outer, lin.outer) and np.array_equal(quad.faces(), lin.faces())
    assert quad.mesh_info()["element_order"] == 2 and replace(spec, element_order=2).token != spec.token
    np.testing.assert_array_equal(quad.frame_offset, lin.frame_offset)
    p = np.array([0.0015, 0.001])
    a, b = lin.solve(p, None), quad.solve(p, None)
    assert a.converged and b.converged
    da, db = a.surface - lin.base_surface(), b.surface - quad.base_surface()
    assert 0 < np.abs(db - da).max() < 0.5 * np.abs(da).max()
    with pytest.raises(SpecError, match="element_order"):
        replace(spec, element_order=3).build()


def test_the_neutral_pose_is_the_rest_state_recorded_as_the_dataset_rest_pose(box_problem, tmp_path):
    """At the head's neutral pose the link map moves nothing, so the FEM surface is the rest surface: that is
    what the manifest's rest_pose promises training."""
    _root, head, spec, _mesh = box_problem
    prob = spec.build()
    neutral = np.array([a.neutral for a in head.actuators])
    sol = prob.solve(neutral, None)
    assert sol.converged
    np.testing.assert_allclose(sol.surface, prob.base_surface(), atol=1e-12)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    generate_dataset(tmp_path / "ds", spec, np.array([[0.001, 0.0], [0.0005, 0.0005]]), head="box",
                     names=head.actuator_names, units=["m", "m"], lo=lo, hi=hi, engine=SerialEngine(), seed=0,
                     sampling={}, progress_stream=None, rest_pose=neutral)
    np.testing.assert_array_equal(PoseDataset(tmp_path / "ds").rest_pose, neutral)


def test_poses_solved_from_rest_do_not_depend_on_each_other_and_a_resume_keeps_the_choice(box_problem, tmp_path):
    """``start="rest"``: every stored pose is the equilibrium a solve from rest reaches, bit for bit, whatever was
    solved before it; the manifest records it, and resuming from the nearest pose instead is refused by name."""
    _root, head, spec, _mesh = box_problem
    prob = spec.build()
    samples = np.array([[0.0015, 0.001], [0.0014, 0.0009], [-0.0005, 0.0012]])
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    kwargs = dict(head="box", names=head.actuator_names, units=["m", "m"], lo=lo, hi=hi, engine=SerialEngine(),
                  seed=0, sampling={}, progress_stream=None)
    generate_dataset(tmp_path / "rest", spec, samples, start="rest", **kwargs)
    generate_dataset(tmp_path / "near", spec, samples, **kwargs)
    rest, near = PoseStore(tmp_path / "rest"), PoseStore(tmp_path / "near")
    assert rest.manifest()["start"] == "rest" and near.manifest()["start"] == "nearest"
    for i, p in enumerate(samples):
        alone = prob.solve(p, None)
        assert np.array_equal(rest.read_pose(i).surface, alone.surface.astype(np.float32))  # as stored
        assert rest.read_pose(i).iterations == alone.iterations
    assert near.read_pose(1).iterations < rest.read_pose(1).iterations  # its neighbour was the start there
    with pytest.raises(SpecError, match="start: folder holds a dataset solved from 'rest'"):
        generate_dataset(tmp_path / "rest", spec, samples, **kwargs)
