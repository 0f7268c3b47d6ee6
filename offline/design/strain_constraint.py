"""The runtime guard's skin-strain measure as a differentiable constraint of the actuation optimization.

The guard's measure (``models.strain_guard.SurfaceStrain``) is, per kept patch k of the outer surface, the
area-weighted mean f_k = Σ_t S_kt ε_t of the triangles' principal engineering strains (ε_min, ε_max), reduced to
(min_k f_k,min, max_k f_k,max). The pose is inside the validated range exactly when every patch is, so the constraint
is the hinge on every patch against limits tightened by a small ``margin``, in augmented-Lagrangian form with a
multiplier λ ≥ 0 per patch and side:

    r_k = max(0, f_k,max − (strain_max − margin) + λ_k / w),   r'_k = max(0, (strain_min + margin) − f_k,min + λ'_k / w)
    P(x) = ½ w Σ (r_k² + r'_k²)

With λ = 0, P is the plain quadratic penalty: zero exactly when every patch lies within the tightened limits. P is
continuously differentiable; its residuals r are Gauss-Newton rows, their Jacobian dr/dx analytic (principal
stretches of G0⁻¹G from the triangle metric) and chained through the FEM sensitivities dx/dp. Between rounds the
optimizer sets λ ← w r (the multiplier update) and raises w when the violation does not shrink, until the exact
measure (the same ``SurfaceStrain.extremes`` the report and the runtime guard use) lies inside
[strain_min, strain_max]; the multipliers let that happen at a moderate w, so the match term keeps its say.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from models.strain_guard import SurfaceStrain, principal_strains, triangle_metric


def strain_jacobian(surface: SurfaceStrain, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-triangle principal strains (T, 2) of surface positions ``pos`` (V, 3) against the rest surface, and
    their derivatives (T, 2, 3, 3) with respect to each triangle's three vertices' coordinates.

    Where the two principal stretches coincide (equibiaxial, e.g. at rest) the larger one is not differentiable;
    there the derivative of the square root of the discriminant is taken as zero.
    """
    pos = np.asarray(pos, dtype=np.float64)
    faces = surface.faces
    g0 = surface.g0
    eps = principal_strains(g0, triangle_metric(pos, faces))
    tri = pos[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    a, b, c = (np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2), np.einsum("ij,ij->i", e2, e2))
    a0, b0, c0 = g0[:, 0], g0[:, 1], g0[:, 2]
    det0 = a0 * c0 - b0 * b0
    det0 = np.where(det0 > 0, det0, np.nan)
    h = 0.5 * (c0 * a - 2.0 * b0 * b + a0 * c) / det0
    d = (a * c - b * b) / det0
    disc = np.sqrt(np.maximum(h * h - d, 0.0))
    # d(h), d(d) with respect to the metric (a, b, c): (T, 3)
    dh = np.stack([0.5 * c0, -b0, 0.5 * a0], axis=1) / det0[:, None]
    dd = np.stack([c, -2.0 * b, a], axis=1) / det0[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        ddisc = np.where(disc[:, None] > 1e-12, (h[:, None] * dh - 0.5 * dd) / disc[:, None], 0.0)
    lam2 = np.stack([h - disc, h + disc], axis=1)  # squared principal stretches
    dlam2 = np.stack([dh - ddisc, dh + ddisc], axis=1)  # (T, 2, 3) w.r.t. (a, b, c)
    lam = np.sqrt(np.maximum(lam2, 1e-300))
    deps_dm = dlam2 / (2.0 * lam[:, :, None])
    # metric w.r.t. vertex coordinates: a = e1·e1, b = e1·e2, c = e2·e2; e1 = x1 − x0, e2 = x2 − x0
    dm = np.zeros((len(faces), 3, 3, 3))  # (T, metric component, vertex, coordinate)
    dm[:, 0, 1] = 2.0 * e1
    dm[:, 0, 0] = -2.0 * e1
    dm[:, 1, 1] = e2
    dm[:, 1, 2] = e1
    dm[:, 1, 0] = -(e1 + e2)
    dm[:, 2, 2] = 2.0 * e2
    dm[:, 2, 0] = -2.0 * e2
    return eps, np.einsum("tsm,tmvc->tsvc", deps_dm, dm)


@dataclass(frozen=True, eq=False)
class StrainConstraint:
    """strain_min ≤ guard measure ≤ strain_max on the outer surface ``surface`` whose vertex i is mesh node
    ``nodes[i]``. ``margin``: how far inside the limits the penalty's hinge sits (strain, e.g. 0.01 = 1 %);
    ``weight``: the penalty's starting weight w (objective units); the optimizer runs at most ``max_rounds``
    multiplier rounds, raising w by ``growth`` (up to ``max_weight``) after a round that did not cut the violation
    to a quarter."""

    surface: SurfaceStrain
    nodes: np.ndarray
    strain_min: float
    strain_max: float
    margin: float = 0.01
    weight: float = 1e4
    growth: float = 10.0
    max_rounds: int = 8
    max_weight: float = 1e6

    def __post_init__(self) -> None:
        nodes = np.asarray(self.nodes, dtype=np.int64).reshape(-1)
        if nodes.shape != (len(self.surface.rest),):
            raise ValueError(f"nodes must give the mesh node of each of the surface's {len(self.surface.rest)} "
                             f"vertices, got {nodes.shape}")
        if not -1.0 < self.strain_min < 0.0 < self.strain_max:
            raise ValueError(f"need -1 < strain_min < 0 < strain_max, got {self.strain_min}, {self.strain_max}")
        if not 0.0 <= self.margin < min(-self.strain_min, self.strain_max):
            raise ValueError(f"margin must be in [0, {min(-self.strain_min, self.strain_max)}), got {self.margin}")
        if not 0 < self.weight <= self.max_weight or not self.growth > 1 or self.max_rounds < 0:
            raise ValueError(f"need 0 < weight <= max_weight, growth > 1, max_rounds >= 0; got {self.weight}, "
                             f"{self.max_weight}, {self.growth}, {self.max_rounds}")
        object.__setattr__(self, "nodes", nodes)
        dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        object.__setattr__(self, "dofs", dofs)

    # ------------------------------------------------------------------ exact measure
    def measure(self, x: np.ndarray) -> tuple[float, float]:
        """The guard's measure (min, max) of the mesh positions x (N, 3): ``SurfaceStrain.extremes``."""
        return self.surface.extremes(np.asarray(x)[self.nodes])

    def inside(self, strain: tuple[float, float]) -> bool:
        """Whether a measure (min, max) lies within [strain_min, strain_max]."""
        return bool(self.strain_min <= strain[0] and strain[1] <= self.strain_max)

    # ------------------------------------------------------------------ penalty
    @property
    def n_patches(self) -> int:
        return int(self.surface.smooth.shape[0])

    def _hinge(self, f: np.ndarray, weight: float, lam: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Shifted hinge arguments (K,) of the max and min sides (positive where the penalty is active)."""
        r_hi = f[:, 1] - (self.strain_max - self.margin)
        r_lo = (self.strain_min + self.margin) - f[:, 0]
        if lam is not None:
            r_hi = r_hi + lam[:, 1] / weight
            r_lo = r_lo + lam[:, 0] / weight
        return r_hi, r_lo

    def residuals(self, x: np.ndarray, weight: float | None = None, lam: np.ndarray | None = None
                  ) -> tuple[np.ndarray, tuple[float, float]]:
        """Hinge residuals (positive parts only: the patch sides where the penalty is active) and the exact measure,
        of the mesh positions x (N, 3); ``lam`` (K, 2): multipliers of the (min, max) sides per patch."""
        f = self.surface.field(np.asarray(x)[self.nodes])
        r_hi, r_lo = self._hinge(f, self.weight if weight is None else weight, lam)
        return np.concatenate([r_hi[r_hi > 0], r_lo[r_lo > 0]]), (float(f[:, 0].min()), float(f[:, 1].max()))

    def penalty(self, x: np.ndarray, weight: float | None = None, lam: np.ndarray | None = None
                ) -> tuple[float, tuple[float, float]]:
        """P(x) = ½ w Σ r² and the exact measure."""
        w = self.weight if weight is None else weight
        r, m = self.residuals(x, w, lam)
        return 0.5 * w * float(r @ r), m

    def multipliers(self, x: np.ndarray, weight: float, lam: np.ndarray | None = None) -> np.ndarray:
        """The multiplier update at x: λ ← w · max(0, hinge argument) (K, 2), (min, max) sides."""
        f = self.surface.field(np.asarray(x)[self.nodes])
        r_hi, r_lo = self._hinge(f, weight, lam)
        return weight * np.stack([np.maximum(r_lo, 0.0), np.maximum(r_hi, 0.0)], axis=1)

    def violation(self, x: np.ndarray) -> float:
        """Largest excess of any patch over the tightened limits (0 when inside them)."""
        f = self.surface.field(np.asarray(x)[self.nodes])
        r_hi, r_lo = self._hinge(f, 1.0, None)
        return float(max(r_hi.max(), r_lo.max(), 0.0))

    def jacobian(self, x: np.ndarray, weight: float | None = None, lam: np.ndarray | None = None
                 ) -> tuple[np.ndarray, sparse.csr_matrix]:
        """Residuals r (as :meth:`residuals`) and dr/dx (n_r, 3N) over all mesh coordinates (sparse)."""
        x = np.asarray(x, dtype=np.float64)
        pos = x[self.nodes]
        eps, deps = strain_jacobian(self.surface, pos)
        f = np.asarray(self.surface.smooth @ eps)
        S = self.surface.smooth
        faces = self.surface.faces
        n_t = len(faces)
        cols = (3 * self.nodes[faces][:, :, None] + np.arange(3)).reshape(n_t, 9)
        rows = np.repeat(np.arange(n_t), 9)
        n_x = 3 * x.shape[0]
        r_hi, r_lo = self._hinge(f, self.weight if weight is None else weight, lam)
        a_hi, a_lo = np.flatnonzero(r_hi > 0), np.flatnonzero(r_lo > 0)
        deps = np.nan_to_num(deps)
        D_hi = sparse.csr_matrix((deps[:, 1].reshape(-1), (rows, cols.reshape(-1))), shape=(n_t, n_x))
        D_lo = sparse.csr_matrix((deps[:, 0].reshape(-1), (rows, cols.reshape(-1))), shape=(n_t, n_x))
        J = sparse.vstack([S[a_hi] @ D_hi, -(S[a_lo] @ D_lo)]).tocsr()
        return np.concatenate([r_hi[a_hi], r_lo[a_lo]]), J


def face_strain_surface(face, mesh=None) -> SurfaceStrain:
    """The guard's measure on a design face's outer surface (``offline.design.face.FaceSkin``): the head's
    ``[skin]`` radius and band, rims of the rigid attachments (skull, link patches) of ``mesh`` left out."""
    from models.strain_guard import DEFAULT_BAND, DEFAULT_RADIUS, skin_number
    from offline.strain_eval import attachment_distance

    head = face.skin.head
    mesh = face.mesh if mesh is None else mesh
    radius = skin_number(head, "radius_mm", DEFAULT_RADIUS * 1e3) * 1e-3
    band = skin_number(head, "band_mm", DEFAULT_BAND * 1e3) * 1e-3
    rim, _ = attachment_distance(head, mesh, face.outer[face.faces])
    return SurfaceStrain(np.asarray(mesh.nodes)[face.outer], face.faces, rim, radius, band)


def face_strain_constraint(face, margin: float = 0.01, weight: float = 1e4) -> StrainConstraint:
    """The constraint of a design face: the head's validated range (``[skin] strain_min``/``strain_max``) on the
    guard's measure of the outer surface (which the thickness design keeps fixed, so it holds on every rest
    shape the design produces)."""
    from models.strain_guard import skin_strain_range

    lo, hi = skin_strain_range(face.skin.head)
    return StrainConstraint(face_strain_surface(face), face.outer, lo, hi, margin=margin, weight=weight)
