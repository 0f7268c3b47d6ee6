"""Material fitting: recovery of known parameters from FEM curves, a real silicone, and optimiser agreement."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from offline.material.fit import ParamSpace, closed_form_forces, fit_measurement
from offline.material.measurements import Measurement, load_measurements
from offline.material.models import MaterialParams
from offline.material.specimen import SpecimenPlan, make_plan
from offline.material.virtual_test import run_plan

DATA = Path(__file__).resolve().parents[3] / "data" / "tensile"


def _measurement(strain: np.ndarray, force: np.ndarray) -> Measurement:
    return Measurement(strain, force, np.arange(2, 2 + strain.size), "synthetic", "strain,force_N")


def _noisy(force: np.ndarray, strain: np.ndarray, level: float, seed: int) -> np.ndarray:
    scale = np.where(strain < 0, np.abs(force[strain < 0]).max(initial=0.0), np.abs(force[strain >= 0]).max())
    return force + level * scale * np.random.default_rng(seed).standard_normal(force.size)


def test_fit_recovers_E_nu_from_noisy_fem_curve() -> None:
    truth = MaterialParams("neo_hookean", 60_000.0, 0.45)
    plan = make_plan("auto")
    strain = np.array([-0.2, -0.15, -0.1, -0.05, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5])
    force = _noisy(run_plan(truth, plan, strain, grips="frictionless"), strain, 0.003, seed=3)
    result = fit_measurement(_measurement(strain, force), plan, method="both", seed=0)
    assert {r.method for r in result.runs} == {"anneal", "lsq"}
    for run in result.runs:
        assert np.isclose(run.params.E, 60_000.0, rtol=0.01)
        assert run.params.nu == pytest.approx(0.45, abs=0.02)
    lsq = next(r for r in result.runs if r.method == "lsq")
    assert abs(lsq.params.nu - 0.45) < 4 * lsq.stderr["nu"] + 1e-3
    assert result.relative_rms < 0.01
    assert "exact for frictionless" in result.surrogate


def test_anneal_alone_and_lsq_alone_agree_without_noise() -> None:
    truth = MaterialParams("neo_hookean", 150_000.0, 0.42)
    plan = make_plan("strip")
    strain = np.linspace(0.02, 0.5, 8)
    force = closed_form_forces(truth, strain, plan)
    sa = fit_measurement(_measurement(strain, force), plan, method="anneal", seed=7)
    ls = fit_measurement(_measurement(strain, force), plan, method="lsq")
    assert sa.method == "anneal" and ls.method == "lsq"
    for r in (sa, ls):
        assert np.isclose(r.params.E, 150_000.0, rtol=1e-4)
        assert r.params.nu == pytest.approx(0.42, abs=2e-3)
        assert r.rms_force_N < 1e-4 * np.abs(force).max()


def test_mooney_rivlin_fit_reproduces_curve() -> None:
    truth = MaterialParams("mooney_rivlin", 80_000.0, 0.46, {"c01": 6_000.0})
    plan = make_plan("auto")
    strain = np.linspace(-0.2, 0.5, 12)
    force = closed_form_forces(truth, strain, plan)
    result = fit_measurement(_measurement(strain, force), plan, model="mooney_rivlin", method="lsq")
    assert result.params.model == "mooney_rivlin"
    assert np.isclose(result.params.E, 80_000.0, rtol=0.01)
    assert result.relative_rms < 1e-3


def test_real_ecoflex_00_30_pins_E_but_not_nu() -> None:
    meas = load_measurements(DATA / "Ecoflex_00-30.csv", make_plan("auto"))
    plan = SpecimenPlan(meas.specimen, meas.specimen)
    result = fit_measurement(meas.select(0.0, 0.5), plan, method="both")
    # README orientation: incompressible neo-Hookean least squares over 0-50 % gives E ≈ 46 kPa
    assert 35_000.0 < result.params.E < 60_000.0
    assert result.relative_rms < 0.08
    ident = result.identifiability["parameters"]
    lo, hi = ident["E"]["ci95"]
    assert ident["E"]["identified"] and lo < result.params.E < hi and (hi - lo) < 0.2 * result.params.E
    # Tension of a near-incompressible rubber barely depends on nu: the fit must say it did not pin it.
    assert not ident["nu"]["identified"]
    assert ident["nu"]["ci95"][1] - ident["nu"]["ci95"][0] > 0.5 * (0.499 - 0.3)
    assert any("tension-only data do not pin nu" in line for line in result.identifiability["summary"])


def test_joint_strip_and_cylinder_fit_identifies_nu_that_the_strip_alone_does_not() -> None:
    from offline.material.measurements import combine_measurements
    from offline.material.specimen import cylinder, strip

    truth = MaterialParams("neo_hookean", 60_000.0, 0.45)
    s_plan, c_plan = SpecimenPlan(strip(), strip()), SpecimenPlan(cylinder(), cylinder())
    eps_t, eps_c = np.linspace(0.05, 0.5, 8), np.linspace(-0.2, -0.02, 6)
    rng = np.random.default_rng(1)
    f_t = closed_form_forces(truth, eps_t, s_plan) * (1 + 0.01 * rng.standard_normal(8))
    f_c = closed_form_forces(truth, eps_c, c_plan) * (1 + 0.01 * rng.standard_normal(6))
    alone = fit_measurement(_measurement(eps_t, f_t), s_plan, method="lsq")
    assert not alone.identifiability["parameters"]["nu"]["identified"]
    # Neither file names its specimen: the auto plan gives the tension file the strip, the compression file the
    # cylinder, and the joint plan keeps each sample on its own specimen (residuals scaled per specimen).
    meas, plan = combine_measurements([_measurement(eps_t, f_t), _measurement(eps_c, f_c)], make_plan("auto"))
    assert [s.kind for s in plan.specimens] == ["strip", "cylinder"]
    joint = fit_measurement(meas, plan, method="lsq")
    nu = joint.identifiability["parameters"]["nu"]
    assert nu["identified"] and nu["ci95"][0] < 0.45 < nu["ci95"][1]
    assert nu["ci95"][1] - nu["ci95"][0] < 0.3 * (alone.identifiability["parameters"]["nu"]["ci95"][1]
                                                  - alone.identifiability["parameters"]["nu"]["ci95"][0])
    E = joint.identifiability["parameters"]["E"]
    assert E["ci95"][0] < 60_000.0 < E["ci95"][1]


def test_param_space_round_trip_and_fixed_nu() -> None:
    space = ParamSpace.build("yeoh", (1e3, 1e6), (0.3, 0.499))
    p = MaterialParams("yeoh", 5e4, 0.4, {"c20": 1000.0, "c30": 50.0})
    q = space.to_params(space.to_vector(p))
    assert np.isclose(q.E, p.E) and np.isclose(q.nu, p.nu)
    assert q.extra["c20"] == pytest.approx(1000.0) and q.extra["c30"] == pytest.approx(50.0)
    fixed = ParamSpace.build("neo_hookean", (1e3, 1e6), (0.47, 0.47))
    assert fixed.names == ("log10_E",) and fixed.to_params(np.array([4.0])).nu == 0.47


def test_too_few_samples_refused() -> None:
    with pytest.raises(ValueError, match="at least 3"):
        fit_measurement(_measurement(np.array([0.1, 0.2]), np.array([0.07, 0.13])), make_plan("strip"))


@pytest.mark.slow
def test_clamped_fit_recovers_parameters_from_clamped_fem_curve() -> None:
    truth = MaterialParams("neo_hookean", 78_000.0, 0.47)
    plan = make_plan("auto")
    strain = np.array([-0.2, -0.1, 0.1, 0.3, 0.5])

    def fem(params: MaterialParams, eps: np.ndarray) -> np.ndarray:
        return run_plan(params, plan, eps, grips="clamped")

    force = fem(truth, strain)
    result = fit_measurement(_measurement(strain, force), plan, method="lsq", grips="clamped", fem_model=fem)
    assert np.isclose(result.params.E, 78_000.0, rtol=0.005)
    assert result.params.nu == pytest.approx(0.47, abs=0.003)
    assert result.fem_sweeps >= 6
    # the frictionless closed form cannot explain clamped data: its best fit is much worse
    naive = fit_measurement(_measurement(strain, force), plan, method="lsq")
    assert naive.relative_rms > 10 * result.relative_rms
