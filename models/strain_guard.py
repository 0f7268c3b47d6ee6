"""Skin-strain guard: is a commanded actuator pose within the strain range the skin silicone was validated for?

The measure (``docs/skin_guard.md``) is the principal engineering strain of the outer skin surface, per triangle
(ε = λ − 1 from the in-plane principal stretches λ), averaged area-weighted over a physical neighbourhood of
``radius`` (default 8 mm, connected skin only), leaving out the triangles whose centroid lies closer than ``band``
(default 7 mm, measured through the skin) to a rigid attachment region (link patches and skull), and reduced to
its extremes: (min over the surface
of the smoothed smaller strain, max of the smoothed larger strain). :class:`SurfaceStrain` computes it on any
surface (the FEM's, the predictor's); :class:`StrainGuard` computes it from the KSNN predictor, relative to the
rest mesh (or the predictor's neutral prediction), in two forms: ``full`` (every vertex, off the control loop)
and the reduced in-cycle ``measure``/``check`` that evaluates only the patches that can come near a limit,
straight from the hidden layer (edge vectors are linear in the hidden activations). numpy and scipy only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import SpecError
from models.kernel_support import kernels_available
from models.kernels_aot import kernel
from models.predictor import DEFAULT_STRAIN_RANGE, KsnnWeights, SkinPredictor

#: Default neighbourhood radius (m) of the area-weighted average: above the coarse sample mesh's 5.6 mm edges,
#: well below the size of a face feature (a lip is ~15 mm tall).
DEFAULT_RADIUS = 0.008
#: Default distance (m) from the rigid attachment regions (through the skin) below which triangles are not measured:
#: about 3.6 mm beside an attachment under the sample skin's 6 mm, more where the skin is thinner.
DEFAULT_BAND = 0.007
#: Reference surfaces the predictor's strain can be measured against: the rest (base) mesh, as the FEM does, or
#: the predictor's own prediction at the neutral pose (cancels its neutral error, but not its pose-dependent one).
REFERENCES = ("rest", "neutral")
#: :meth:`StrainGuard.limit`'s verdicts, by the compiled limit's return code.
VERDICTS = ("ok", "limited", "held")
#: Attachment distance file format (``[paths] skin_guard`` of a head).
FOOTPRINT_FORMAT = "likeness-skin-attachment-distance"


# ---------------------------------------------------------------------------- per-triangle geometry
def triangle_metric(pos: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """First fundamental form of each triangle in its edge basis: (..., T, 3) = (e1·e1, e1·e2, e2·e2)."""
    tri = np.take(pos, faces, axis=-2)
    e1 = tri[..., 1, :] - tri[..., 0, :]
    e2 = tri[..., 2, :] - tri[..., 0, :]
    return np.stack([np.einsum("...i,...i->...", e1, e1), np.einsum("...i,...i->...", e1, e2),
                     np.einsum("...i,...i->...", e2, e2)], axis=-1)


def principal_strains(g0: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Principal engineering strains (ε_min, ε_max) from reference and deformed metrics (..., T, 3) → (..., T, 2).

    Eigenvalues of G0⁻¹G are the squared principal stretches; a degenerate reference triangle gives NaN.
    """
    a0, b0, c0 = g0[..., 0], g0[..., 1], g0[..., 2]
    det0 = a0 * c0 - b0 * b0
    det0 = np.where(det0 > 0, det0, np.nan)
    a, b, c = g[..., 0], g[..., 1], g[..., 2]
    half_tr = 0.5 * (c0 * a - 2.0 * b0 * b + a0 * c) / det0
    det = (a * c - b * b) / det0
    disc = np.sqrt(np.maximum(half_tr * half_tr - det, 0.0))
    lo = np.sqrt(np.maximum(half_tr - disc, 0.0)) - 1.0
    hi = np.sqrt(half_tr + disc) - 1.0
    return np.stack([lo, hi], axis=-1)


class SurfaceStrain:
    """The strain measure on one triangulated surface at rest (``rest`` (V, 3) m, ``faces`` (T, 3)).

    ``rim_distance`` (T,) is each triangle's rest-centroid distance to the nearest rigid attachment region (the
    inner-surface triangles and edges of the attachment node sets); triangles closer than ``band`` are left out.
    Each kept triangle's value is the area-weighted mean over the kept triangles whose centroids lie within
    ``radius`` of its own and are reached through the mesh within 1.5 ``radius`` (so the upper and lower lip,
    close in space across the mouth, do not mix).
    """

    def __init__(self, rest: np.ndarray, faces: np.ndarray, rim_distance: np.ndarray | None = None,
                 radius: float = DEFAULT_RADIUS, band: float = DEFAULT_BAND) -> None:
        from scipy import sparse
        from scipy.sparse.csgraph import dijkstra
        from scipy.spatial import cKDTree

        rest = np.asarray(rest, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if rest.ndim != 2 or rest.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"rest must be (V, 3) and faces (T, 3), got {rest.shape} and {faces.shape}")
        if not radius > 0 or not band >= 0:
            raise ValueError(f"radius must be positive and band non-negative, got {radius}, {band}")
        self.rest, self.faces = rest, faces
        self.radius, self.band = float(radius), float(band)
        tri = rest[faces]
        self.centroids = tri.mean(axis=1)
        self.areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        self.g0 = triangle_metric(rest, faces)
        n_tri = len(faces)
        kept = self.areas > 0
        self.rim_distance = None
        if rim_distance is not None:
            rim = np.asarray(rim_distance, dtype=np.float64)
            if rim.shape != (n_tri,):
                raise ValueError(f"rim_distance must give one distance per triangle ({n_tri}), got {rim.shape}")
            self.rim_distance = rim
            kept &= rim >= band
        self.kept = kept
        kidx = np.flatnonzero(kept)
        if kidx.size == 0:
            raise ValueError("no triangle is left for the strain measure (band too wide for this surface)")
        # Edge-adjacency of triangles, weighted by centroid distance (graph geodesic for connectivity).
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        owner = np.repeat(np.arange(n_tri), 3)
        key = edges[:, 0] * (len(rest) + 1) + edges[:, 1]
        order = np.argsort(key, kind="stable")
        ks, ow = key[order], owner[order]
        same = np.flatnonzero(ks[1:] == ks[:-1])
        i, j = ow[same], ow[same + 1]
        w = np.linalg.norm(self.centroids[i] - self.centroids[j], axis=1) + 1e-12
        graph = sparse.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(n_tri, n_tri)).tocsr()
        tree = cKDTree(self.centroids[kidx])
        rows, cols, vals = [], [], []
        for start in range(0, kidx.size, 512):
            chunk = kidx[start:start + 512]
            geo = dijkstra(graph, indices=chunk, limit=1.5 * radius)
            for r, t in enumerate(chunk):
                near = kidx[tree.query_ball_point(self.centroids[t], radius)]
                near = near[np.isfinite(geo[r, near])]
                wts = self.areas[near]
                rows.append(np.full(near.size, start + r))
                cols.append(near)
                vals.append(wts / wts.sum())
        self.smooth = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                        shape=(kidx.size, n_tri))

    @property
    def kept_area_fraction(self) -> float:
        return float(self.areas[self.kept].sum() / self.areas.sum())

    def triangle_strains(self, positions: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
        """Unsmoothed principal strains (..., T, 2) of ``positions`` vs ``reference`` (default: the rest surface)."""
        g0 = self.g0 if reference is None else triangle_metric(np.asarray(reference, dtype=np.float64), self.faces)
        return principal_strains(g0, triangle_metric(np.asarray(positions, dtype=np.float64), self.faces))

    def field(self, positions: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
        """Smoothed principal strains at the kept triangles: (K, 2) for one surface, (B, K, 2) for a batch."""
        eps = self.triangle_strains(positions, reference)
        if eps.ndim == 2:
            return np.asarray(self.smooth @ eps)
        b, t, _ = eps.shape
        return np.asarray(self.smooth @ eps.transpose(1, 0, 2).reshape(t, 2 * b)).reshape(-1, b, 2).transpose(1, 0, 2)

    def extremes(self, positions: np.ndarray, reference: np.ndarray | None = None) -> tuple[float, float]:
        """The measure of one surface: (smallest smoothed ε_min, largest smoothed ε_max) over the kept skin."""
        f = self.field(positions, reference)
        return float(f[:, 0].min()), float(f[:, 1].max())


# ---------------------------------------------------------------------------- footprint file
def save_footprint(path: str | Path, rim_distance: np.ndarray, sets: Mapping[str, int],
                   provenance: Mapping[str, Any]) -> None:
    """Write each outer-surface triangle's distance to the rigid attachments (predictor face order) as .npz."""
    import io
    import json

    from models.atomic import write_bytes

    buf = io.BytesIO()
    np.savez(buf, format=np.array(FOOTPRINT_FORMAT), rim_distance=np.asarray(rim_distance, dtype=np.float64),
             sets=np.array(json.dumps(dict(sets))), provenance=np.array(json.dumps(dict(provenance), default=str)))
    write_bytes(Path(path), buf.getvalue())


def load_footprint(path: str | Path, n_triangles: int) -> np.ndarray:
    """Per-triangle attachment distances (T,) from a file written by :func:`save_footprint`."""
    source = str(path)
    try:
        with np.load(path) as z:
            fmt = str(z["format"]) if "format" in z.files else ""
            rim = np.asarray(z["rim_distance"], dtype=np.float64) if "rim_distance" in z.files else None
    except (OSError, ValueError) as exc:
        raise SpecError(source, "file", f"cannot read the attachment distances: {exc}") from exc
    if fmt != FOOTPRINT_FORMAT or rim is None:
        raise SpecError(source, "format", f"not a {FOOTPRINT_FORMAT} file (needs 'format' and 'rim_distance')")
    if rim.shape != (n_triangles,):
        raise SpecError(source, "rim_distance", f"must give the predictor's {n_triangles} triangles", rim.shape)
    if not np.all(np.isfinite(rim)) or np.any(rim < 0):
        raise SpecError(source, "rim_distance", "distances must be finite and non-negative")
    return rim


# ---------------------------------------------------------------------------- the guard
@dataclass(frozen=True)
class GuardCalibration:
    """How the reduced check's patches were chosen and how it agreed with the full measure on its own sample."""

    samples: int
    seed: int
    patches: int
    patches_total: int
    vertices: int
    agreement: float


#: Bump when the patch selection changes, so cached selections are recomputed.
SELECTION_VERSION = 1


def _cache_dir() -> Path:
    import os

    base = os.environ.get("LIKENESS_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "likeness")
    return Path(base) / "strain_guard"


def _cache_load(key: str) -> tuple[np.ndarray, float, int] | None:
    path = _cache_dir() / f"{key}.npz"
    try:
        with np.load(path) as z:
            return z["rows"].astype(np.intp), float(z["agreement"]), int(z["samples"])
    except (OSError, KeyError, ValueError):
        return None


def _cache_save(key: str, rows: np.ndarray, agreement: float, samples: int) -> None:
    from models.atomic import atomic_path

    path = _cache_dir() / f"{key}.npz"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez(tmp, rows=rows, agreement=agreement, samples=samples)
    except OSError:
        pass  # no writable cache: the selection is recomputed next time


def skin_number(head: Any, key: str, default: float) -> float:
    """A finite number from the head's ``[skin]`` table (SpecError naming the key otherwise)."""
    value = head.section("skin").get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise SpecError(str(head.source), f"skin.{key}", "must be a finite number", value)
    return float(value)


def skin_strain_range(head: Any) -> tuple[float, float]:
    """The validated principal-strain range of the head's skin, ``[skin] strain_min``/``strain_max``."""
    lo = skin_number(head, "strain_min", DEFAULT_STRAIN_RANGE[0])
    hi = skin_number(head, "strain_max", DEFAULT_STRAIN_RANGE[1])
    if not -1.0 < lo < 0.0 < hi:
        raise SpecError(str(head.source), "skin.strain_min", "need -1 < strain_min < 0 < strain_max", (lo, hi))
    return lo, hi


def edge_basis(E: np.ndarray, tol: float = 1e-5, worth: float = 0.7) -> tuple[np.ndarray, np.ndarray]:
    """The reduced check's offset maps (float32). ``E`` (3, H, v), each axis' offsets of the measured vertices per
    hidden activation, lies in the span of the output layer's directions, q of them per axis (the output rank: fewer
    than H for a network trained with ``--output-rank``). Returns (Q, F) with the offsets h_k E_k = (Q_k h_k) F_k,
    Q_k (q, H) orthonormal rows and F_k = Q_k E_k (q, v): q (H + v) instead of v H multiplications per axis. Singular
    values under ``tol`` of an axis' largest are dropped (float32 noise); where q exceeds ``worth`` H the basis saves
    too little for its second product and is not used: Q (3, 0, H) and F = E. An axis of lower rank gets zero rows."""
    H = E.shape[1]
    bases = []
    for k in range(3):
        U, sv, _ = np.linalg.svd(E[k], full_matrices=False)
        bases.append(U[:, sv > tol * sv[0]].T if sv[0] > 0 else np.zeros((0, H)))
    q = max(len(b) for b in bases)
    if q > worth * H:
        return np.zeros((3, 0, H), np.float32), np.ascontiguousarray(E, dtype=np.float32)
    Q = np.zeros((3, q, H))
    for k, b in enumerate(bases):
        Q[k, q - len(b):] = b
    return np.ascontiguousarray(Q, dtype=np.float32), np.ascontiguousarray(np.matmul(Q, E), dtype=np.float32)


class StrainGuard:
    """Accept or refuse commanded actuator poses (SI, the head's actuator order) by the skin-strain measure.

    ``reference``: "rest" measures the predicted surface against the rest mesh, as the FEM's is measured;
    "neutral" against the predictor's own neutral prediction (which reads exactly zero at neutral, but on the
    sample head agrees less with the FEM at large strains: ``docs/skin_guard.md``). Poses outside the
    predictor's trained range are evaluated at the range (clamped) but always refused by :meth:`check` (the
    model cannot vouch for them); non-finite poses are refused.

    The reduced check evaluates only a few patches (kept triangles' neighbourhoods), directly from the hidden
    activations: on ``samples`` seeded poses over the trained range, a greedy cover picks patches until, for
    every sample and every level (a fraction ``levels`` of each limit) that the full measure crosses, a chosen
    patch crosses it too.
    """

    def __init__(self, predictor: SkinPredictor, neutral: np.ndarray,
                 strain_range: tuple[float, float] = DEFAULT_STRAIN_RANGE, rim_distance: np.ndarray | None = None,
                 radius: float = DEFAULT_RADIUS, band: float = DEFAULT_BAND, samples: int = 6000,
                 levels: tuple[float, ...] = (0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.25), seed: int = 0,
                 names: tuple[str, ...] | None = None, reference: str = "rest") -> None:
        lo_s, hi_s = (float(x) for x in strain_range)
        if not -1.0 < lo_s < 0.0 < hi_s:
            raise ValueError(f"strain_range must satisfy -1 < min < 0 < max, got {strain_range}")
        self.predictor = predictor
        self.compiled = kernels_available()  # the in-cycle measure compiled (models._skin_kernels) or numpy
        self.names = tuple(names) if names is not None else predictor.actuator_names
        if len(self.names) != predictor.n_actuators:
            raise ValueError(f"names lists {len(self.names)} actuators, the predictor {predictor.n_actuators}")
        self.strain_range = (lo_s, hi_s)
        w: KsnnWeights = predictor.weights
        self.weights = w
        self.lo, self.hi = w.lo.copy(), w.hi.copy()
        self.neutral = np.asarray(neutral, dtype=np.float64)
        if self.neutral.shape != (predictor.n_actuators,):
            raise ValueError(f"neutral must have shape ({predictor.n_actuators},), got {self.neutral.shape}")
        base = predictor.base_vertices.astype(np.float64)
        self.surface = SurfaceStrain(base, predictor.faces, rim_distance, radius, band)
        if reference not in REFERENCES:
            raise ValueError(f"reference must be one of {', '.join(REFERENCES)}, got {reference!r}")
        self.reference_kind = reference
        self.reference = base + w.offsets(self.neutral) if reference == "neutral" else base
        self._g0 = triangle_metric(self.reference, predictor.faces)
        H = w.hidden
        self._W1 = np.ascontiguousarray(np.concatenate([w.W1[k].T for k in range(3)], axis=0))  # (3H, A)
        self._b1 = np.concatenate(list(w.b1))
        self._scale = 1.0 / (w.hi - w.lo)
        self._shift = -w.lo * self._scale
        # Full-field numpy forward (for calibration): positions = base + b2 + h_k @ W2_k.
        self._H = H
        self._select(samples, tuple(levels), seed)
        self.measure_hidden(np.zeros(3 * H))  # compile (or load the cached kernel) now, never in a control cycle
        if self.compiled:  # and the control cycle's guard stage (the types it is called with; no groups here)
            mid = 0.5 * (self.lo + self.hi)
            self.limit_constrained(mid, mid, mid, self.lo, self.hi, (np.zeros(4, np.int64), np.zeros(0)), steps=1)

    # ------------------------------------------------------------------ construction
    @classmethod
    def for_head(cls, head: Any, predictor: SkinPredictor | None = None) -> StrainGuard | None:
        """The guard of a head: ``[paths] predictor`` (None when absent), ``[paths] skin_guard`` (attachment
        distances, optional) and ``[skin]`` ``strain_min``/``strain_max``/``radius_mm``/``band_mm``."""
        path = head.path("predictor")
        if predictor is None:
            if path is None or not Path(path).is_file():
                return None
            predictor = SkinPredictor(path)
        cfg = head.section("skin")

        def number(key: str, default: float) -> float:
            return skin_number(head, key, default)

        lo, hi = skin_strain_range(head)
        radius, band = number("radius_mm", DEFAULT_RADIUS * 1e3), number("band_mm", DEFAULT_BAND * 1e3)
        reference = cfg.get("reference", "rest")
        if reference not in REFERENCES:
            raise SpecError(str(head.source), "skin.reference", f"must be one of {', '.join(REFERENCES)}", reference)
        if radius <= 0:
            raise SpecError(str(head.source), "skin.radius_mm", "must be positive", radius)
        if band < 0:
            raise SpecError(str(head.source), "skin.band_mm", "must not be negative", band)
        fp = head.path("skin_guard")
        rim = None
        if fp is not None:
            if not Path(fp).is_file():
                raise SpecError(str(head.source), "paths.skin_guard", "file not found", str(fp))
            rim = load_footprint(fp, len(predictor.faces))
        neutral = np.clip(head.neutral_pose, predictor.lo, predictor.hi)
        return cls(predictor, neutral, (lo, hi), rim, radius * 1e-3, band * 1e-3,
                   names=tuple(a.name for a in head.actuators), reference=reference)

    def _full_hidden_field(self, P: np.ndarray) -> np.ndarray:
        """Smoothed field (B, K, 2) of a batch of normalized poses, numpy forward pass (calibration)."""
        w = self.weights
        h = np.tanh(np.einsum("ba,kah->bkh", P, w.W1) + w.b1)
        pos = np.einsum("bkh,khv->bvk", h, w.W2) + w.b2.T + self.surface.rest
        eps = principal_strains(self._g0, triangle_metric(pos, self.surface.faces))  # (B, T, 2)
        b, t, _ = eps.shape
        out = self.surface.smooth @ eps.transpose(1, 0, 2).reshape(t, 2 * b)  # one sparse product for the batch
        return np.asarray(out).reshape(-1, b, 2).transpose(1, 0, 2)

    def _select(self, samples: int, levels: tuple[float, ...], seed: int) -> None:
        """Choose the reduced check's patches, or take them from the cache (the choice is a pure function of the
        predictor, the attachment footprint and the settings, and takes seconds)."""
        import hashlib

        w = self.weights
        h = hashlib.sha256()
        for arr in (w.W1, w.b1, w.W2, w.b2, w.lo, w.hi, self.surface.rest, self.surface.faces, self.surface.kept,
                    self.reference, self.neutral):
            h.update(np.ascontiguousarray(arr).tobytes())
        h.update(repr((self.strain_range, samples, levels, seed, self.surface.smooth.nnz, SELECTION_VERSION)).encode())
        key = h.hexdigest()[:32]
        cached = _cache_load(key)
        if cached is None:
            rows, agreement, n = self._choose(samples, levels, seed)
            _cache_save(key, rows, agreement, n)
        else:
            rows, agreement, n = cached
        self._prepare(rows, agreement, n, seed)

    def _choose(self, samples: int, levels: tuple[float, ...], seed: int,
                track: float = 0.02) -> tuple[np.ndarray, float, int]:
        rng = np.random.default_rng(seed)
        A = self.weights.n_actuators
        X = rng.uniform(0.0, 1.0, (samples, A))
        edge = rng.random((samples, A)) < 0.15
        X[edge] = rng.integers(0, 2, edge.sum()).astype(float)
        X = np.vstack([X, self.weights.normalize(self.neutral)[None, :]])
        lo_s, hi_s = self.strain_range
        fields = np.concatenate([self._full_hidden_field(X[i:i + 250]) for i in range(0, len(X), 250)])
        # Greedy cover: for every sample and level (a fraction of each limit), if the full measure crosses the
        # level, some chosen patch must cross it too; so the reduced extreme tracks the full one near the limits.
        items = []
        for lev in levels:
            full_lo = fields[:, :, 0].min(axis=1) <= lev * lo_s
            full_hi = fields[:, :, 1].max(axis=1) >= lev * hi_s
            items.append(fields[full_lo, :, 0] <= lev * lo_s)
            items.append(fields[full_hi, :, 1] >= lev * hi_s)
        # Tracking: near a limit (the full extreme beyond 0.7 of it), a chosen patch must come within ``track``
        # (a fraction of the limit) of the full extreme, so a pose just past the limit is seen as past it.
        fmin, fmax = fields[:, :, 0].min(axis=1), fields[:, :, 1].max(axis=1)
        near_lo, near_hi = fmin <= 0.7 * lo_s, fmax >= 0.7 * hi_s
        items.append(fields[near_lo, :, 0] <= (fmin[near_lo] - track * lo_s)[:, None])
        items.append(fields[near_hi, :, 1] >= (fmax[near_hi] - track * hi_s)[:, None])
        cover = np.concatenate(items)  # (items, patches)
        crit = np.zeros(fields.shape[1], dtype=bool)
        open_rows = np.ones(len(cover), dtype=bool)
        while open_rows.any():
            gain = cover[open_rows].sum(axis=0)
            best = int(np.argmax(gain))
            if gain[best] == 0:
                break
            crit[best] = True
            open_rows &= ~cover[:, best]
        crit[np.argmin(fields[-1, :, 0])] = True  # at least one patch each side even when nothing crosses
        crit[np.argmax(fields[-1, :, 1])] = True
        rows = np.flatnonzero(crit)
        # Agreement of the reduced check with the full measure on the selection sample itself.
        full_ok = (fields[:, :, 0].min(axis=1) >= lo_s) & (fields[:, :, 1].max(axis=1) <= hi_s)
        red = fields[:, rows]
        red_ok = (red[:, :, 0].min(axis=1) >= lo_s) & (red[:, :, 1].max(axis=1) <= hi_s)
        return rows, float(np.mean(full_ok == red_ok)), len(X)

    def _prepare(self, rows: np.ndarray, agreement: float, n_samples: int, seed: int) -> None:
        """The reduced check's arrays for the chosen patches ``rows``."""
        S = self.surface.smooth[rows]
        tri = np.unique(S.indices)
        verts = np.unique(self.surface.faces[tri])
        # The measured triangles' vertex offsets are linear in each axis' hidden activations, d_k = h_k @ E_k
        # (float32: offsets of millimetres keep ~1e-7 relative precision), and each triangle's two edge vectors are
        # differences of its corners' offsets plus the edges at h = 0, e0 (the rest surface with b2): maps over the
        # vertices are about half the size of maps over the edges, which a frame reads from memory.
        w = self.weights
        f = self.surface.faces[tri]
        n_t = len(tri)
        corners = np.searchsorted(verts, f)  # (n_t, 3): each corner among the measured vertices
        pos0 = self.surface.rest + w.b2.T  # (V, 3)
        E = np.ascontiguousarray(w.W2[:, :, verts])  # (3, H, v)
        e0 = np.zeros((3, 2, n_t))
        for k in range(3):
            for j, c in enumerate((1, 2)):
                e0[k, j] = pos0[f[:, c], k] - pos0[f[:, 0], k]
        self._Q, self._E = edge_basis(E)
        self._tri = np.ascontiguousarray(corners.T, dtype=np.int64)  # (3, n_t)
        self._e0 = np.ascontiguousarray(e0.reshape(3, 1, 2 * n_t), dtype=np.float32)
        self._n_t = n_t
        g0 = self._g0[tri]
        det0 = g0[:, 0] * g0[:, 2] - g0[:, 1] ** 2
        # half the trace of G0⁻¹G = Σ C ⊙ M over the symmetric 2×2 metric M; det(G0⁻¹G) = det M / det0.
        self._C = np.ascontiguousarray(np.array([[0.5 * g0[:, 2], -0.5 * g0[:, 1]],
                                                 [-0.5 * g0[:, 1], 0.5 * g0[:, 0]]]) / det0)
        self._pm = np.array([[-1.0], [1.0]])
        self._idet = 1.0 / det0
        self._S = np.ascontiguousarray(S[:, tri].toarray().T)  # (n_t, P) dense: small
        # the same by patch, sparse, for the compiled measure (0.4 % of the dense matrix: what a cycle reads)
        Sp = S[:, tri].tocsr()
        Sp.sort_indices()
        self._S_ptr = Sp.indptr.astype(np.int64)
        self._S_idx = Sp.indices.astype(np.int64)
        self._S_w = Sp.data.astype(np.float64)
        self.calibration = GuardCalibration(samples=n_samples, seed=seed, patches=len(rows),
                                            patches_total=int(self.surface.kept.sum()), vertices=len(verts),
                                            agreement=agreement)

    # ------------------------------------------------------------------ in-cycle (reduced)
    def hidden(self, p: np.ndarray) -> np.ndarray:
        """Hidden activations (3H,) at raw pose p, clamped to the trained range."""
        x = np.clip(p * self._scale + self._shift, 0.0, 1.0)
        return np.tanh(self._W1 @ x + self._b1)

    def kernel_arrays(self) -> tuple[np.ndarray, ...]:
        """The arrays the compiled reduced measure takes after the hidden activations (Q, E, e0, the triangles'
        corners, C, 1/det, and the patch weights by patch: pointers, triangles, weights; :func:`edge_basis` for Q
        and E)."""
        return self._Q, self._E, self._e0, self._tri, self._C, self._idet, self._S_ptr, self._S_idx, self._S_w

    def search_args(self, steps: int) -> tuple[np.ndarray, np.ndarray, float, float, int]:
        """What the compiled guard search takes besides the measure's arrays: the input scale and shift, the strain
        range and the bisections (:func:`models.kernel_args.pack_frame_args`)."""
        return self._scale, self._shift, float(self.strain_range[0]), float(self.strain_range[1]), int(steps)

    def measure_hidden(self, h: np.ndarray) -> tuple[float, float]:
        """Reduced measure (min, max) from hidden activations (3H,) (for callers that already have them);
        compiled (:mod:`models._skin_kernels`) unless ``compiled`` is False."""
        if self.compiled:
            lo, hi = kernel("reduced_measure")(np.asarray(h, dtype=np.float64), *self.kernel_arrays())
            return float(lo), float(hi)
        return self.measure_hidden_numpy(h)

    def measure_hidden_numpy(self, h: np.ndarray) -> tuple[float, float]:
        """The reduced measure in numpy: the reference for the compiled one."""
        n = self._n_t
        hk = h.reshape(3, 1, self._H).astype(np.float32)
        if self._Q.shape[1]:
            hk = np.matmul(hk, self._Q.transpose(0, 2, 1))  # (3, 1, q): the coordinates the offsets depend on
        d = np.matmul(hk, self._E)[:, 0]  # (3, v) the measured vertices' offsets
        t = self._tri
        e = np.concatenate([d[:, t[1]] - d[:, t[0]], d[:, t[2]] - d[:, t[0]]], axis=1)[:, None]  # (3, 1, 2n)
        e += self._e0
        e = e.reshape(3, 2, n)
        m = np.einsum("kin,kjn->ijn", e, e)  # (2, 2, n) metric of each triangle
        half_tr = np.einsum("ijn,ijn->n", m, self._C)  # half the trace of G0⁻¹G
        det = (m[0, 0] * m[1, 1] - m[0, 1] * m[0, 1]) * self._idet
        disc = half_tr * half_tr
        disc -= det
        np.sqrt(np.maximum(disc, 0.0, out=disc), out=disc)
        lam = self._pm * disc  # (2, n): −disc, +disc
        lam += half_tr
        np.sqrt(np.maximum(lam, 0.0, out=lam), out=lam)
        out = lam @ self._S  # (2, P) patch means of the principal stretches
        return float(out[0].min()) - 1.0, float(out[1].max()) - 1.0

    def measure(self, p: np.ndarray) -> tuple[float, float]:
        """Reduced (min, max) of the measure at raw pose p (clamped to the trained range)."""
        return self.measure_hidden(self.hidden(np.asarray(p, dtype=np.float64)))

    def in_range(self, p: np.ndarray) -> bool:
        """True when p is finite and inside the predictor's trained range (within 1e-6 of its span)."""
        p = np.asarray(p, dtype=np.float64)
        tol = 1e-6 * (self.hi - self.lo)
        return bool(np.all(np.isfinite(p)) and np.all(p >= self.lo - tol) and np.all(p <= self.hi + tol))

    def passes(self, strain: tuple[float, float]) -> bool:
        return self.strain_range[0] <= strain[0] and strain[1] <= self.strain_range[1]

    def check(self, p: np.ndarray) -> bool:
        """In-cycle decision: True if p is in the trained range and its reduced measure is within the limits."""
        x = p * self._scale + self._shift  # normalized; NaN fails both comparisons below
        if not (x.min() >= -1e-6 and x.max() <= 1.0 + 1e-6):  # float32 range metadata
            if np.shape(p) != self.lo.shape:
                raise ValueError(f"pose must have shape {self.lo.shape}, got {np.shape(p)}")
            return False
        lo, hi = self.measure_hidden(np.tanh(self._W1 @ x + self._b1))
        return self.strain_range[0] <= lo and hi <= self.strain_range[1]

    # ------------------------------------------------------------------ off-loop (full)
    def full(self, p: np.ndarray) -> tuple[float, float]:
        """Full measure (min, max) from a full predictor pass (every vertex; ONNX), at p clamped to the range."""
        p = np.clip(np.asarray(p, dtype=np.float64), self.lo, self.hi)
        pos = self.predictor.predict(p).astype(np.float64)
        return self.surface.extremes(pos, self.reference)

    def full_batch(self, P: np.ndarray) -> np.ndarray:
        """Full measure (B, 2) of a batch of raw poses (clamped to the range)."""
        X = self.weights.normalize(np.clip(np.asarray(P, dtype=np.float64), self.lo, self.hi))
        out = []
        for i in range(0, len(X), 250):
            f = self._full_hidden_field(X[i:i + 250])
            out.append(np.stack([f[:, :, 0].min(axis=1), f[:, :, 1].max(axis=1)], axis=1))
        return np.concatenate(out) if out else np.zeros((0, 2))

    # ------------------------------------------------------------------ motion
    def limit(self, p_from: np.ndarray, p_to: np.ndarray, steps: int = 5) -> tuple[np.ndarray, str]:
        """``p_to`` if it passes ("ok"); else the furthest passing point of the segment from ``p_from`` found by
        ``steps`` bisections ("limited"); else ``p_from`` ("held"). One compiled call where the measure is compiled
        (:func:`models._skin_kernels.guard_limit`), else :meth:`limit_by_checks`: the same poses and verdicts."""
        p_to = np.asarray(p_to, dtype=np.float64)
        if not self.compiled:
            return self.limit_by_checks(p_from, p_to, steps)
        if p_to.shape != self.lo.shape:
            raise ValueError(f"pose must have shape {self.lo.shape}, got {p_to.shape}")
        out = np.empty_like(p_to)
        verdict = kernel("guard_limit")(np.asarray(p_from, dtype=np.float64), p_to, int(steps), out, self._scale,
                                        self._shift, self._W1, self._b1, *self.strain_range, *self.kernel_arrays())
        return out, VERDICTS[verdict]

    def limit_constrained(self, targets: np.ndarray, current: np.ndarray, p_from: np.ndarray, lo: np.ndarray,
                          hi: np.ndarray, groups: tuple[np.ndarray, np.ndarray], steps: int = 5
                          ) -> tuple[np.ndarray, str | None]:
        """``targets`` constrained to ``[lo, hi]`` and the actuator ``groups`` (holds, NaN, from ``current``; the
        groups packed by :func:`models.kernel_args.pack_constraints`), then :meth:`limit` from ``p_from``, in one
        compiled call (:func:`models._skin_kernels.guard_step`): the control cycle's guard stage. The verdict is
        None when the constrained target is ``p_from`` itself (nothing checked). Needs the compiled measure
        (:attr:`compiled`)."""
        if not self.compiled:
            raise RuntimeError("limit_constrained needs the compiled strain measure (numba)")
        out = np.empty_like(p_from)
        code = kernel("guard_step")(targets, current, p_from, int(steps), out, lo, hi, *groups, self._scale,
                                    self._shift, self._W1, self._b1, *self.strain_range, *self.kernel_arrays())
        return out, None if code < 0 else VERDICTS[code]

    def limit_by_checks(self, p_from: np.ndarray, p_to: np.ndarray, steps: int = 5) -> tuple[np.ndarray, str]:
        """:meth:`limit` as a bisection over :meth:`check` (the compiled limit's reference)."""
        p_to = np.asarray(p_to, dtype=np.float64)
        if self.check(p_to):
            return p_to, "ok"
        base = np.asarray(p_from, dtype=np.float64)
        d = p_to - base
        lo_t, hi_t, found = 0.0, 1.0, False
        for _ in range(steps):
            mid = 0.5 * (lo_t + hi_t)
            if self.check(base + mid * d):
                lo_t, found = mid, True
            else:
                hi_t = mid
        if found:
            return base + lo_t * d, "limited"
        return base.copy(), "held"
