"""Homogeneous uniaxial closed form: against the FEM package's independent reference and known limits."""

from __future__ import annotations

import numpy as np
import pytest

from offline.fem.closed_form import uniaxial
from offline.material.closed_form import lateral_stretch, principal_piola, uniaxial_nominal_stress
from offline.material.models import MaterialParams

CASES = [
    MaterialParams("neo_hookean", 78_000.0, 0.47),
    MaterialParams("neo_hookean", 40_000.0, 0.3),
    MaterialParams("mooney_rivlin", 78_000.0, 0.47, {"c01": 6_000.0}),
    MaterialParams("yeoh", 78_000.0, 0.45, {"c20": -800.0, "c30": 300.0}),
]


@pytest.mark.parametrize("params", CASES, ids=lambda p: p.model)
def test_matches_fem_reference_closed_form(params: MaterialParams) -> None:
    # offline.fem.closed_form solves the same problem from first_piola with brentq: an independent implementation
    stretches = 1.0 + np.array([-0.2, -0.05, 0.01, 0.2, 0.5])
    stress, lat = uniaxial_nominal_stress(params, stretches)
    fem_material = params.to_fem_material()
    for s, p, lt in zip(stretches, stress, lat, strict=True):
        p_ref, l_ref = uniaxial(fem_material, s)
        assert p == pytest.approx(p_ref, rel=1e-9, abs=1e-9)
        assert lt == pytest.approx(l_ref, rel=1e-10)


def test_small_strain_limit_gives_E_and_nu() -> None:
    params = MaterialParams("neo_hookean", 78_000.0, 0.47)
    eps = 1e-6
    stress, lat = uniaxial_nominal_stress(params, np.array([1.0 + eps]))
    assert stress[0] / eps == pytest.approx(78_000.0, rel=1e-4)
    assert (lat[0] - 1.0) / eps == pytest.approx(-0.47, rel=1e-4)


def test_nearly_incompressible_limit() -> None:
    params = MaterialParams("neo_hookean", 60_000.0, 0.49999)
    lam = 1.0 + np.linspace(-0.2, 0.5, 8)
    stress, lat = uniaxial_nominal_stress(params, lam)
    np.testing.assert_allclose(stress, params.mu * (lam - lam**-2), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(lat, lam**-0.5, rtol=1e-4)


def test_lateral_stress_is_zero_and_signs() -> None:
    params = CASES[2]
    lam = 1.0 + np.linspace(-0.3, 0.8, 12)
    lat = lateral_stretch(params, lam)
    p = principal_piola(params, lam, lat, lat)
    assert np.max(np.abs(p[1])) < 1e-6 * np.max(np.abs(p[0]))
    moved = np.abs(lam - 1.0) > 1e-12
    assert np.all(np.sign(p[0][moved]) == np.sign(lam - 1.0)[moved])


def test_bad_parameters_refused() -> None:
    with pytest.raises(ValueError, match="nu"):
        MaterialParams("neo_hookean", 78_000.0, 0.5)
    with pytest.raises(ValueError, match="E must be positive"):
        MaterialParams("neo_hookean", -1.0, 0.4)
    with pytest.raises(ValueError, match="no parameter"):
        MaterialParams("neo_hookean", 1.0, 0.4, {"c01": 1.0})
    with pytest.raises(ValueError, match="c01"):
        MaterialParams("mooney_rivlin", 78_000.0, 0.47, {"c01": 1e6})
    with pytest.raises(ValueError, match="unknown material model"):
        MaterialParams("ogden", 1.0, 0.4)
