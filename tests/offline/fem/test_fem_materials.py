"""Material factories, modulus conversions and the NumPy stress reference."""

from __future__ import annotations

import numpy as np
import pytest

from offline.fem import (
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


def test_modulus_conversions_round_trip() -> None:
    mu, kappa = mu_kappa_from_E_nu(1.0e5, 0.45)
    assert mu == pytest.approx(1.0e5 / 2.9) and kappa == pytest.approx(1.0e5 / 0.3)
    assert E_nu_from_mu_kappa(mu, kappa) == pytest.approx((1.0e5, 0.45))
    m = neo_hookean_from_E_nu(1.0e5, 0.45, density=1100.0)
    assert m.params["mu"] == pytest.approx(mu) and m.density == 1100.0
    assert m.shear_modulus == pytest.approx(mu) and m.bulk_modulus == pytest.approx(kappa)


def test_small_strain_shear_modulus_of_each_model() -> None:
    assert mooney_rivlin(1e4, 2e3, 1e5).shear_modulus == pytest.approx(2.4e4)
    assert yeoh(1e4, -100.0, 10.0, 1e5).shear_modulus == pytest.approx(2e4)
    # simple shear slope at γ → 0 equals μ for every model
    for m in (neo_hookean(3e4, 3e5), mooney_rivlin(1e4, 2e3, 1e5), yeoh(1e4, -100.0, 10.0, 1e5)):
        F = np.eye(3)
        F[0, 1] = 1e-6
        assert first_piola(m, F)[0, 1] / 1e-6 == pytest.approx(m.shear_modulus, rel=1e-5)


@pytest.mark.parametrize("mat", [neo_hookean(3e4, 3e5), mooney_rivlin(1e4, 2e3, 1e5), yeoh(1e4, -300.0, 50.0, 1e5)],
                         ids=["nh", "mr", "yeoh"])
def test_first_piola_is_the_energy_gradient(mat: Material) -> None:
    rng = np.random.default_rng(4)
    F = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    assert np.linalg.det(F) > 0
    P = first_piola(mat, F)
    h = 1e-7
    fd = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            dF = np.zeros((3, 3))
            dF[i, j] = h
            fd[i, j] = (energy_density(mat, F + dF) - energy_density(mat, F - dF)) / (2 * h)
    assert np.allclose(P, fd, rtol=1e-6, atol=1e-6 * np.abs(P).max())
    assert energy_density(mat, np.eye(3)) == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(first_piola(mat, np.eye(3)), 0.0, atol=1e-9)


def test_bad_parameters_are_named() -> None:
    with pytest.raises(ValueError, match="unknown material model 'ogden'"):
        Material("ogden", {"mu": 1.0})
    with pytest.raises(ValueError, match=r"missing parameter\(s\) \['kappa'\]"):
        Material("neo_hookean", {"mu": 1.0})
    with pytest.raises(ValueError, match="kappa must be > 0"):
        neo_hookean(1e4, -1.0)
    with pytest.raises(ValueError, match="mu must be > 0"):
        neo_hookean(0.0, 1e5)
    with pytest.raises(ValueError, match="nu"):
        mu_kappa_from_E_nu(1e5, 0.5)


def test_one_material_vocabulary_across_config_fit_and_fem() -> None:
    from models.material import MATERIAL_MODELS, SHAPE_PARAMS, SkinMaterial
    from offline.fem.materials import MODEL_PARAMS
    from offline.material.models import MODEL_NAMES, MaterialParams

    assert tuple(MODEL_PARAMS) == MATERIAL_MODELS == MODEL_NAMES
    for name in MATERIAL_MODELS:
        shape = {k: 1000.0 for k in SHAPE_PARAMS[name]}
        skin = SkinMaterial(name, 80_000.0, 0.45, shape)
        fem = MaterialParams.from_skin_material(skin).to_fem_material(skin.density)
        assert fem.name == name
        assert fem.shear_modulus == pytest.approx(80_000.0 / (2 * 1.45))  # the same small-strain E and nu
