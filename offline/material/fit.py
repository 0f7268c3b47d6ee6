"""Fit hyperelastic parameters (E, ν and model shape parameters) to measured uniaxial force–strain samples.

Two optimisers, as in the physical face-cloning pipeline: simulated annealing (``scipy.optimize.dual_annealing``
with a fixed seed: a global search over the bounded box) and gradient-based least squares
(``scipy.optimize.least_squares``, trust-region reflective, started from a small-strain estimate). ``both`` runs
the two independently and keeps the one with the lower error; parameter standard errors come from the
least-squares Jacobian when it ran.

Forward model (force at each measured strain):

- frictionless grips: the homogeneous closed form (:mod:`offline.material.closed_form`); for these grips it IS
  the FEM answer (the virtual test is homogeneous and tets reproduce affine fields exactly), at ~1 ms per curve.
- clamped grips: the FEM virtual test. To keep simulated annealing affordable the fit runs on the closed form
  multiplied by a per-strain correction FEM/closed-form evaluated at the current estimate, re-evaluated with the
  FEM until the parameters stop moving (a few FEM sweeps); the reported error is that of the final FEM curve.

Residuals are scaled per specimen (by the largest measured |force| on that specimen), so a compression cylinder's
hundreds of newtons do not drown a tension strip's fractions of a newton.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize

from models.material import MATERIAL_FIT_FORMAT
from offline.material import closed_form
from offline.material.measurements import Measurement
from offline.material.models import NU_RANGE, MaterialParams, canonical_model_name
from offline.material.specimen import PointPlan, SpecimenPlan

METHODS: tuple[str, ...] = ("anneal", "lsq", "both")

#: Bounds of the model shape parameters, relative to c10 = μ/2 (dimensionless), used as fit variables.
_SHAPE_BOUNDS: dict[str, dict[str, tuple[float, float]]] = {
    "neo_hookean": {},
    "mooney_rivlin": {"c01_share": (0.0, 0.95)},  # c01 = share · μ/2, c10 = (1 − share) · μ/2
    "yeoh": {"c20_rel": (-0.2, 1.0), "c30_rel": (0.0, 0.5)},  # c20 = rel · c10, c30 = rel · c10
}

ForceModel = Callable[[MaterialParams, np.ndarray], np.ndarray]


def closed_form_forces(params: MaterialParams, strain: np.ndarray, plan: SpecimenPlan) -> np.ndarray:
    """Axial forces (N) of the homogeneous (frictionless-grip) test at each strain, per the specimen plan."""
    eps = np.asarray(strain, dtype=float)
    return closed_form.uniaxial_nominal_stress(params, 1.0 + eps)[0] * plan.area_per_point(eps)


@dataclass(frozen=True)
class ParamSpace:
    """Maps the optimiser's vector (log10 E, ν, shape parameters) to :class:`MaterialParams` and back."""

    model: str
    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    fixed_nu: float | None = None

    @classmethod
    def build(cls, model: str, E_bounds: tuple[float, float], nu_bounds: tuple[float, float]) -> ParamSpace:
        """Parameter box for ``model``; ν is held fixed when its bounds coincide."""
        model = canonical_model_name(model)
        lo_nu, hi_nu = nu_bounds
        if not (-1.0 < lo_nu <= hi_nu < 0.5):
            raise ValueError(f"nu bounds must satisfy -1 < lo <= hi < 0.5, got {nu_bounds!r}")
        if not (0.0 < E_bounds[0] < E_bounds[1]):
            raise ValueError(f"E bounds must satisfy 0 < lo < hi, got {E_bounds!r}")
        names = ["log10_E"]
        lower = [math.log10(E_bounds[0])]
        upper = [math.log10(E_bounds[1])]
        fixed = None
        if hi_nu - lo_nu > 1e-12:
            names.append("nu")
            lower.append(lo_nu)
            upper.append(hi_nu)
        else:
            fixed = lo_nu
        for name, (lo, hi) in _SHAPE_BOUNDS[model].items():
            names.append(name)
            lower.append(lo)
            upper.append(hi)
        return cls(model, tuple(names), np.array(lower), np.array(upper), fixed)

    def to_params(self, x: np.ndarray) -> MaterialParams:
        """The material for optimiser vector ``x``."""
        v = dict(zip(self.names, (float(t) for t in x), strict=True))
        E = 10.0 ** v["log10_E"]
        nu = self.fixed_nu if self.fixed_nu is not None else v["nu"]
        half_mu = 0.5 * E / (2.0 * (1.0 + nu))
        extra: dict[str, float] = {}
        if self.model == "mooney_rivlin":
            extra["c01"] = v["c01_share"] * half_mu
        elif self.model == "yeoh":
            extra["c20"] = v["c20_rel"] * half_mu
            extra["c30"] = v["c30_rel"] * half_mu
        return MaterialParams(self.model, E, nu, extra)

    def to_vector(self, params: MaterialParams) -> np.ndarray:
        """Optimiser vector of ``params`` (clipped into the box)."""
        half_mu = params.mu / 2.0
        v = {"log10_E": math.log10(params.E), "nu": params.nu}
        if params.model == "mooney_rivlin":
            v["c01_share"] = params.extra["c01"] / half_mu
        elif params.model == "yeoh":
            v["c20_rel"] = params.extra["c20"] / half_mu
            v["c30_rel"] = params.extra["c30"] / half_mu
        x = np.array([v[n] for n in self.names])
        return np.clip(x, self.lower, self.upper)

    def midpoint(self) -> np.ndarray:
        """Centre of the box."""
        return 0.5 * (self.lower + self.upper)


@dataclass
class RunResult:
    """Outcome of one optimiser run."""

    method: str
    params: MaterialParams
    cost: float
    evaluations: int
    seconds: float
    stderr: dict[str, float] = field(default_factory=dict)
    message: str = ""


@dataclass
class FitResult:
    """The chosen fit, its errors against the measurements, and every run for comparison."""

    params: MaterialParams
    method: str
    grips: str
    surrogate: str
    strain: np.ndarray
    measured: np.ndarray
    simulated: np.ndarray
    runs: list[RunResult]
    fem_sweeps: int = 0
    runs_simulated: dict[str, np.ndarray] = field(default_factory=dict)
    #: Which parameters the data identify, with 95 % intervals (:mod:`offline.material.identify`).
    identifiability: dict[str, Any] = field(default_factory=dict)

    @property
    def rms_force_N(self) -> float:
        """Root-mean-square force error (N)."""
        return float(np.sqrt(np.mean((self.simulated - self.measured) ** 2)))

    @property
    def max_abs_error_N(self) -> float:
        """Largest absolute force error (N)."""
        return float(np.max(np.abs(self.simulated - self.measured)))

    @property
    def relative_rms(self) -> float:
        """RMS force error divided by the largest measured |force|."""
        return self.rms_force_N / max(float(np.max(np.abs(self.measured))), 1e-300)

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly summary."""
        return {
            "format": MATERIAL_FIT_FORMAT,
            "format_version": 1,
            "model": self.params.model,
            "E_Pa": self.params.E,
            "nu": self.params.nu,
            "params": self.params.as_dict(),
            "method": self.method,
            "grips": self.grips,
            "forward_model": self.surrogate,
            "fem_sweeps": self.fem_sweeps,
            "n_points": int(self.strain.size),
            "strain_min": float(self.strain.min()),
            "strain_max": float(self.strain.max()),
            "rms_force_error_N": self.rms_force_N,
            "relative_rms_force_error": self.relative_rms,
            "max_abs_force_error_N": self.max_abs_error_N,
            "identifiability": self.identifiability,
            "runs": [
                {"method": r.method, "E_Pa": r.params.E, "nu": r.params.nu, "params": r.params.as_dict(),
                 "scaled_cost": r.cost, "evaluations": r.evaluations, "seconds": r.seconds,
                 "stderr": r.stderr, "message": r.message}
                for r in self.runs
            ],
        }


def small_strain_modulus(strain: np.ndarray, force: np.ndarray, area: np.ndarray) -> float:
    """Rough Young's modulus (Pa) from the samples nearest zero strain (median secant), for start values/bounds."""
    eps = np.asarray(strain, dtype=float)
    order = np.argsort(np.abs(eps))
    picked = [i for i in order if abs(eps[i]) >= 1e-3][: max(3, eps.size // 4)]
    if not picked:
        raise ValueError("need samples at |strain| >= 0.001 to estimate a modulus")
    secant = force[picked] / (area[picked] * eps[picked])
    secant = secant[secant > 0]
    if secant.size == 0:
        raise ValueError("measured forces do not follow the sign of the strain near zero strain")
    # the secant at strain ε of a rubber under tension is below E, in compression above: the median is a fair start
    return float(np.median(secant))


def _scales(strain: np.ndarray, force: np.ndarray, plan: SpecimenPlan) -> np.ndarray:
    scale = np.ones_like(force)
    for _spec, mask in plan.for_strains(strain):
        scale[mask] = max(float(np.max(np.abs(force[mask]))), 1e-12)
    return scale


def _run_anneal(space: ParamSpace, cost: Callable[[np.ndarray], float], seed: int, maxiter: int) -> RunResult:
    t0 = time.perf_counter()
    res = optimize.dual_annealing(cost, bounds=list(zip(space.lower, space.upper, strict=True)), seed=seed,
                                  maxiter=maxiter)
    return RunResult("anneal", space.to_params(res.x), float(res.fun), int(res.nfev), time.perf_counter() - t0,
                     message=str(res.message[0] if isinstance(res.message, list) else res.message))


def _run_lsq(space: ParamSpace, residual: Callable[[np.ndarray], np.ndarray], x0: np.ndarray) -> RunResult:
    t0 = time.perf_counter()
    res = optimize.least_squares(residual, x0, bounds=(space.lower, space.upper), x_scale="jac", method="trf",
                                 xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
    params = space.to_params(res.x)
    stderr: dict[str, float] = {}
    n, p = res.fun.size, res.x.size
    if n > p:
        s2 = float(res.fun @ res.fun) / (n - p)
        try:
            cov = np.linalg.inv(res.jac.T @ res.jac) * s2
            for i, name in enumerate(space.names):
                sd = math.sqrt(max(cov[i, i], 0.0))
                if name == "log10_E":
                    stderr["E_Pa"] = params.E * math.log(10.0) * sd
                else:
                    stderr[name] = sd
        except np.linalg.LinAlgError:
            stderr = {}
    return RunResult("lsq", params, float(res.fun @ res.fun) / max(n, 1), int(res.nfev), time.perf_counter() - t0,
                     stderr=stderr, message=str(res.message))


def fit_measurement(
    meas: Measurement,
    plan: SpecimenPlan | PointPlan,
    *,
    model: str = "neo_hookean",
    method: str = "both",
    grips: str = "frictionless",
    nu_bounds: tuple[float, float] = NU_RANGE,
    E_bounds: tuple[float, float] | None = None,
    seed: int = 0,
    anneal_maxiter: int = 300,
    fem_model: ForceModel | None = None,
    max_fem_sweeps: int = 6,
) -> FitResult:
    """Fit ``model`` to ``meas`` tested on ``plan``; see the module docstring for the forward models.

    ``fem_model(params, strain) -> force`` is the FEM virtual test, required for clamped grips.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if grips not in ("frictionless", "clamped"):
        raise ValueError(f"grips must be 'frictionless' or 'clamped', got {grips!r}")
    if len(meas) < 3:
        raise ValueError(f"{meas.source}: need at least 3 samples in the fitted strain range, got {len(meas)}")
    strain, force = meas.strain, meas.force
    area = plan.area_per_point(strain)
    if E_bounds is None:
        E0 = small_strain_modulus(strain, force, area)
        E_bounds = (E0 / 30.0, E0 * 30.0)
    space = ParamSpace.build(model, E_bounds, nu_bounds)
    scale = _scales(strain, force, plan)

    correction: dict[str, Callable[[MaterialParams], np.ndarray | float]] = {"fn": lambda _p: 1.0}

    def surrogate_forces(params: MaterialParams) -> np.ndarray:
        return closed_form_forces(params, strain, plan) * correction["fn"](params)

    def residual(x: np.ndarray) -> np.ndarray:
        r = (surrogate_forces(space.to_params(x)) - force) / scale
        return np.where(np.isfinite(r), r, 1e3)

    def cost(x: np.ndarray) -> float:
        r = residual(x)
        return float(r @ r) / r.size

    x_start = space.to_vector(MaterialParams(space.model, math.sqrt(E_bounds[0] * E_bounds[1]),
                                             space.fixed_nu if space.fixed_nu is not None else 0.45))
    if grips == "frictionless":
        surrogate = "closed form (homogeneous uniaxial, zero lateral stress): exact for frictionless grips"
        runs = _optimise(space, method, residual, cost, x_start, seed, anneal_maxiter)
        best = min(runs, key=lambda r: r.cost)
        simulated = closed_form_forces(best.params, strain, plan)
        runs_sim = {r.method: closed_form_forces(r.params, strain, plan) for r in runs}
        return FitResult(best.params, best.method, grips, surrogate, strain, force, simulated, runs, 0, runs_sim,
                         _identify(space, residual, best.params, strain))

    if fem_model is None:
        raise ValueError("clamped grips need the FEM virtual test (fem_model)")
    surrogate = ("FEM virtual test (clamped grips). Optimisers ran on the closed form times the FEM/closed-form "
                 "force ratio, tabulated with the FEM over nu (forces scale exactly with E at fixed nu) and "
                 "corrected with the FEM at the estimate until the surrogate matched the FEM there")
    # 1. shape parameters and a rough E from the frictionless closed form (cheap)
    rough = _run_lsq(space, residual, x_start).params
    # 2. FEM/closed-form ratio over a nu grid (even in log(1 - 2 nu), where the ratio varies smoothly)
    nu_grid = _nu_grid(space)
    sweeps = 0
    table = []
    for nu in nu_grid:
        p = space.to_params(_with_nu(space, space.to_vector(rough), nu))
        table.append(_ratio(fem_model(p, strain), closed_form_forces(p, strain, plan), strain))
        sweeps += 1
    if len(nu_grid) > 1:
        from scipy.interpolate import PchipInterpolator

        interp = PchipInterpolator(np.log(1.0 - 2.0 * np.asarray(nu_grid)), np.array(table), axis=0)

        def ratio_of(params: MaterialParams) -> np.ndarray:
            return interp(math.log(1.0 - 2.0 * params.nu))
    else:
        fixed_ratio = table[0]

        def ratio_of(params: MaterialParams) -> np.ndarray:
            return fixed_ratio

    local = np.ones_like(force)
    correction["fn"] = lambda params: ratio_of(params) * local
    runs = _optimise(space, method, residual, cost, x_start, seed, anneal_maxiter)
    best = min(runs, key=lambda r: r.cost)
    # 3. make the surrogate exact at the estimate (interpolation and shape-parameter effects) and re-fit
    fem_at_best: dict[str, np.ndarray] = {}
    for _ in range(max_fem_sweeps):
        fem_curve = fem_model(best.params, strain)
        sweeps += 1
        fem_at_best = {best.method: fem_curve}
        mismatch = np.max(np.abs(fem_curve - surrogate_forces(best.params)) / scale)
        if mismatch < 1e-5:
            break
        local = local * _ratio(fem_curve, surrogate_forces(best.params), strain)
        correction["fn"] = lambda params, local=local: ratio_of(params) * local
        runs = _optimise(space, method, residual, cost, space.to_vector(best.params), seed, anneal_maxiter)
        best = min(runs, key=lambda r: r.cost)
    runs_sim: dict[str, np.ndarray] = {}
    for r in runs:
        if r.method in fem_at_best and r.params == best.params:
            runs_sim[r.method] = fem_at_best[r.method]
        else:
            runs_sim[r.method] = fem_model(r.params, strain)
            sweeps += 1
    return FitResult(best.params, best.method, grips, surrogate, strain, force, runs_sim[best.method], runs, sweeps,
                     runs_sim, _identify(space, residual, best.params, strain))


def _identify(space: ParamSpace, residual: Callable[[np.ndarray], np.ndarray], params: MaterialParams,
              strain: np.ndarray) -> dict[str, Any]:
    """Identifiability at the chosen estimate, in the optimiser's own parameters (see :mod:`.identify`)."""
    from offline.material.identify import identifiability

    return identifiability(space.names, space.to_vector(params), space.lower, space.upper, residual, strain,
                           space.fixed_nu)


def _nu_grid(space: ParamSpace, n: int = 5) -> list[float]:
    """ν values for the clamped-grip ratio table: the fixed ν, or n points even in log(1 − 2ν) over the bounds."""
    if "nu" not in space.names:
        return [float(space.fixed_nu)]
    i = space.names.index("nu")
    lo, hi = float(space.lower[i]), float(space.upper[i])
    t = np.linspace(math.log(1.0 - 2.0 * hi), math.log(1.0 - 2.0 * lo), n)  # increasing t: nu from hi to lo
    return [float(v) for v in (1.0 - np.exp(t)) / 2.0]


def _with_nu(space: ParamSpace, x: np.ndarray, nu: float) -> np.ndarray:
    y = np.array(x, dtype=float)
    if "nu" in space.names:
        y[space.names.index("nu")] = nu
    return y


def _ratio(fem: np.ndarray, cf: np.ndarray, strain: np.ndarray) -> np.ndarray:
    """FEM / closed-form force ratio per point; near zero strain (both ~0) the nearest well-defined ratio."""
    ok = np.abs(cf) > 1e-9 * max(float(np.max(np.abs(cf))), 1e-300)
    ratio = np.ones_like(fem)
    ratio[ok] = fem[ok] / cf[ok]
    if ok.any() and not ok.all():
        idx = np.flatnonzero(ok)
        for i in np.flatnonzero(~ok):
            ratio[i] = ratio[idx[np.argmin(np.abs(strain[idx] - strain[i]))]]
    return ratio


def _optimise(space: ParamSpace, method: str, residual: Callable[[np.ndarray], np.ndarray],
              cost: Callable[[np.ndarray], float], x_start: np.ndarray, seed: int, maxiter: int) -> list[RunResult]:
    runs = []
    if method in ("anneal", "both"):
        runs.append(_run_anneal(space, cost, seed, maxiter))
    if method in ("lsq", "both"):
        runs.append(_run_lsq(space, residual, x_start))
    return runs
