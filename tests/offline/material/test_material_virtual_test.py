"""FEM virtual uniaxial test: frictionless grips reproduce the closed form; clamped grips are stiffer."""

from __future__ import annotations

import numpy as np
import pytest

from offline.material.closed_form import uniaxial_nominal_stress
from offline.material.models import MaterialParams
from offline.material.specimen import cylinder, make_plan, strip
from offline.material.virtual_test import MeshSettings, run_plan, run_specimen, specimen_mesh

PARAMS = MaterialParams("neo_hookean", 78_000.0, 0.47)
STRAINS = np.array([-0.2, -0.1, 0.0, 0.1, 0.3, 0.5])


def _closed_form(params: MaterialParams, strains: np.ndarray, plan) -> np.ndarray:
    return uniaxial_nominal_stress(params, 1.0 + strains)[0] * plan.area_per_point(strains)


def test_frictionless_matches_closed_form_across_range() -> None:
    # auto plan: cylinder for compression, strip for tension, as the command does by default
    plan = make_plan("auto")
    forces = run_plan(PARAMS, plan, STRAINS, grips="frictionless")
    expected = _closed_form(PARAMS, STRAINS, plan)
    moved = STRAINS != 0.0
    assert forces[~moved] == pytest.approx(0.0, abs=1e-9)
    rel = np.abs(forces[moved] / expected[moved] - 1.0)
    assert rel.max() < 0.005, rel
    assert np.all(np.sign(forces[moved]) == np.sign(STRAINS[moved]))


@pytest.mark.parametrize("params", [MaterialParams("mooney_rivlin", 50_000.0, 0.45, {"c01": 5_000.0}),
                                    MaterialParams("yeoh", 50_000.0, 0.45, {"c20": 1_000.0, "c30": 100.0})],
                         ids=lambda p: p.model)
def test_frictionless_other_models_and_quadratic_tets(params: MaterialParams) -> None:
    strains = np.array([0.25, 0.5])
    forces = run_specimen(params, strip(), strains, grips="frictionless", mesh_settings=MeshSettings(order=2))
    expected = uniaxial_nominal_stress(params, 1.0 + strains)[0] * strip().area
    np.testing.assert_allclose(forces, expected, rtol=0.005)


def test_clamped_grips_are_stiffer() -> None:
    for spec, strains in ((strip(), np.array([0.2, 0.5])), (cylinder(), np.array([-0.2, -0.1]))):
        free = run_specimen(PARAMS, spec, strains, grips="frictionless")
        clamped = run_specimen(PARAMS, spec, strains, grips="clamped")
        assert np.all(np.abs(clamped) > np.abs(free) * 1.005), (spec.kind, clamped, free)
    # the squat bonded cylinder is far stiffer (shape factor ~1, nearly incompressible); the slender strip barely
    comp = run_specimen(PARAMS, cylinder(), np.array([-0.1]), grips="clamped")[0]
    ref = run_specimen(PARAMS, cylinder(), np.array([-0.1]), grips="frictionless")[0]
    assert comp / ref > 1.5


def test_cylinder_mesh_has_true_cross_section() -> None:
    spec = cylinder()
    for order in (1, 2):
        mesh, axis = specimen_mesh(spec, MeshSettings(order=order))
        assert axis == 2
        p = np.asarray(mesh.nodes)[np.asarray(mesh.tets)[:, :4]]
        vol = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])).sum() / 6
        assert vol == pytest.approx(spec.area * spec.length, rel=1e-9)
        assert len(mesh.node_sets["grip_fixed"]) > 0 and len(mesh.node_sets["grip_moving"]) > 0


def test_bad_strain_refused() -> None:
    with pytest.raises(ValueError, match="strains"):
        run_specimen(PARAMS, strip(), np.array([0.1, np.nan]))
    with pytest.raises(ValueError, match="grips"):
        run_specimen(PARAMS, strip(), np.array([0.1]), grips="glued")

