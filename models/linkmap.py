"""The link map m(p): actuator vector → 6-DoF pose of every skin attachment link.

Per link, the position of its tracked frame (metres, head frame) and its rotation relative to the
neutral orientation (a rotation vector, radians, head frame) are quadratic polynomials of the normalised
actuator values ``x = (p - neutral) / half_range`` of the actuators that move that link, fitted by least
squares from tracked samples (:func:`fit_linkmap`). The pose is ``[Rot(r(p)) · R0, t(p)]``.

The file (JSON, versioned, written atomically) carries the actuator names and order, the normalisation,
per-link coefficients, residuals, sample counts, hold-out error and provenance. :meth:`LinkMap.check_against`
refuses a map whose actuators or links do not match a head config, naming the offending names.

All values are SI: actuators in rad (rotary) or m (linear), positions in m, rotations in rad.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_text
from models.errors import SpecError
from models.jsonfile import load_json
from models.rigid import (
    invert,
    matrix_to_quat,
    matrix_to_rotvec,
    quat_to_matrix,
    rotation_angle,
    rotvec_to_matrix,
)

FORMAT = "likeness.linkmap"
VERSION = 1


# ---------------------------------------------------------------------------- features
#: The highest polynomial degree a map file may have (a redesigned head's map of a linkage that bends strongly over
#: its range needs 5 to follow it within 0.05 mm: :data:`offline.design.mechanism_design_head.MAP_TRIES`).
MAX_DEGREE = 5


def n_features(k: int, degree: int = 2) -> int:
    """Number of polynomial features (all monomials up to ``degree``) of ``k`` inputs."""
    return math.comb(k + degree, degree)


def _monomials(k: int, degree: int) -> list[tuple[int, ...]]:
    """The monomials in feature order: constant, linear, then products i<=j (<=l ...) by degree."""
    return [c for d in range(degree + 1) for c in itertools.combinations_with_replacement(range(k), d)]


def quad_features(x: np.ndarray, degree: int = 2) -> np.ndarray:
    """Polynomial features of ``x`` with shape ``(n, k)`` → ``(n, F)``; degree 2: ``[1, x_i, x_i x_j (i<=j)]``."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    n, k = x.shape
    cols = []
    for combo in _monomials(k, degree):
        c = np.ones(n)
        for i in combo:
            c = c * x[:, i]
        cols.append(c)
    return np.stack(cols, axis=1)


def quad_feature_gradient(x: np.ndarray, degree: int = 2) -> np.ndarray:
    """d(features)/dx at one point ``x`` of shape ``(k,)`` → ``(F, k)``."""
    x = np.asarray(x, dtype=float)
    k = x.shape[0]
    monos = _monomials(k, degree)
    G = np.zeros((len(monos), k))
    for row, combo in enumerate(monos):
        for pos, i in enumerate(combo):
            rest = combo[:pos] + combo[pos + 1:]
            G[row, i] += math.prod(float(x[j]) for j in rest)
    return G


# ---------------------------------------------------------------------------- the map
@dataclass
class LinkFit:
    """One link's fitted model: quadratic in the link's own actuators (``actuators``, map order).

    ``coef`` has shape ``(F, 6)``: columns are x, y, z (m) and the rotation vector relative to
    ``rotation0`` (rad). A rigid link has no actuators and one constant row.
    """

    name: str
    actuators: tuple[str, ...]
    coef: np.ndarray
    rotation0: np.ndarray
    rigid: bool = False
    samples: int = 0
    rejected: int = 0
    residual: dict[str, float] = field(default_factory=dict)
    holdout: dict[str, float] = field(default_factory=dict)
    config_actuators: tuple[str, ...] = ()
    selection: str = "data"


class LinkMap:
    """Fitted m(p) for one head; evaluate with :meth:`poses`, :meth:`transforms`, :meth:`jacobian`."""

    def __init__(
        self,
        actuators: Sequence[str],
        neutral: Sequence[float],
        scale: Sequence[float],
        links: Mapping[str, LinkFit],
        head: str = "",
        holdout_rms_mm: float | None = None,
        provenance: Mapping[str, Any] | None = None,
        source: str = "<linkmap>",
        units: Mapping[str, tuple[str, float]] | None = None,
        degree: int = 2,
    ) -> None:
        self.actuators: tuple[str, ...] = tuple(actuators)
        #: Polynomial degree of every link's fit (2: the calibrated quadratic; 3: a map tabulated from a mechanism).
        self.degree = int(degree)
        self.neutral = np.asarray(neutral, dtype=float)
        self.scale = np.asarray(scale, dtype=float)
        if self.neutral.shape != (len(self.actuators),) or self.scale.shape != self.neutral.shape:
            raise ValueError("neutral and scale need one value per actuator")
        if np.any(self.scale <= 0):
            raise ValueError("scale must be positive")
        self.links: dict[str, LinkFit] = dict(links)
        self.head = head
        self.holdout_rms_mm = holdout_rms_mm
        self.provenance: dict[str, Any] = dict(provenance or {})
        #: Per actuator: the config unit and its factor to SI (e.g. ("deg", 0.01745...)), when known.
        self.units: dict[str, tuple[str, float]] = {k: (str(u), float(f)) for k, (u, f) in dict(units or {}).items()}
        self.source = source
        self._index = {a: i for i, a in enumerate(self.actuators)}
        self._link_idx = {n: np.array([self._index[a] for a in f.actuators], dtype=int) for n, f in self.links.items()}
        self._neutral_pose_inv = {
            n: invert(p) for n, p in self._poses_from_vector(self.neutral).items()
        }

    # ------------------------------------------------------------------ evaluation
    def vector(self, actuators: Mapping[str, float] | Sequence[float] | np.ndarray) -> np.ndarray:
        """Actuator vector in map order; a mapping may omit actuators (they take their neutral value)."""
        if isinstance(actuators, Mapping):
            p = self.neutral.copy()
            for name, value in actuators.items():
                i = self._index.get(name)
                if i is None:
                    raise ValueError(f"unknown actuator {name!r}; the link map has: {', '.join(self.actuators)}")
                p[i] = float(value)
            return p
        p = np.asarray(actuators, dtype=float)
        if p.shape != self.neutral.shape:
            raise ValueError(f"expected {len(self.actuators)} actuator values, got shape {p.shape}")
        return p

    def from_config_units(self, actuators: Mapping[str, float]) -> dict[str, float]:
        """Actuator values in config units (degrees, mm) → SI, using the units stored with the map."""
        out = {}
        for name, value in actuators.items():
            if name not in self._index:
                raise ValueError(f"unknown actuator {name!r}; the link map has: {', '.join(self.actuators)}")
            if name not in self.units:
                raise ValueError(f"the link map does not record the unit of {name!r}; pass SI values")
            out[name] = float(value) * self.units[name][1]
        return out

    def normalise(self, p: np.ndarray) -> np.ndarray:
        """Normalised actuator values ``(p - neutral) / scale`` (any leading shape)."""
        return (np.asarray(p, dtype=float) - self.neutral) / self.scale

    def predict(self, P: np.ndarray) -> dict[str, np.ndarray]:
        """Vectorised prediction for actuator vectors ``P`` of shape ``(n, A)``: per link ``(n, 6)`` [t, r]."""
        X = self.normalise(np.atleast_2d(P))
        out = {}
        for name, fit in self.links.items():
            phi = quad_features(X[:, self._link_idx[name]], self.degree)
            out[name] = phi @ fit.coef
        return out

    def _poses_from_vector(self, p: np.ndarray) -> dict[str, np.ndarray]:
        x = self.normalise(p)
        out = {}
        for name, fit in self.links.items():
            y = quad_features(x[self._link_idx[name]][None, :], self.degree)[0] @ fit.coef
            T = np.eye(4)
            T[:3, :3] = rotvec_to_matrix(y[3:]) @ fit.rotation0
            T[:3, 3] = y[:3]
            out[name] = T
        return out

    def poses(self, actuators: Mapping[str, float] | Sequence[float] | np.ndarray) -> dict[str, np.ndarray]:
        """Each link's tracked frame as a 4x4 pose in the head frame (SI) at these actuator values."""
        return self._poses_from_vector(self.vector(actuators))

    def transforms(self, actuators: Mapping[str, float] | Sequence[float] | np.ndarray) -> dict[str, np.ndarray]:
        """Each link's rigid transform from its neutral pose (4x4, head frame, SI): ``x' = T @ x``.

        Applies to any point fixed to the link (e.g. its skin nodes); identity at the neutral actuator values.
        """
        poses = self._poses_from_vector(self.vector(actuators))
        return {n: P @ self._neutral_pose_inv[n] for n, P in poses.items()}

    def jacobian(self, actuators: Mapping[str, float] | Sequence[float] | np.ndarray) -> dict[str, np.ndarray]:
        """d[t (m); r (rad)]/dp per link, shape ``(6, A)`` in map actuator order (zero columns for others).

        ``r`` is the rotation vector relative to the neutral orientation (head frame), as fitted.
        """
        x = self.normalise(self.vector(actuators))
        out = {}
        for name, fit in self.links.items():
            idx = self._link_idx[name]
            J = np.zeros((6, len(self.actuators)))
            if idx.size:
                G = quad_feature_gradient(x[idx], self.degree)  # (F, k)
                J[:, idx] = (fit.coef.T @ G) / self.scale[idx]
            out[name] = J
        return out

    # ------------------------------------------------------------------ validation
    def evaluate(self, P: np.ndarray, observations: Mapping[str, LinkObservations]) -> dict[str, dict[str, float]]:
        """Errors of the map against observed poses: per link rms/max position (mm) and rms/max angle (deg)."""
        pred = self.predict(P)
        out = {}
        for name, obs in observations.items():
            if name not in self.links:
                continue
            ok = obs.valid
            if not np.any(ok):
                continue
            out[name] = _errors(pred[name][ok], self.links[name].rotation0, obs.positions[ok], obs.rotations()[ok])
        return out

    def check_against(self, head: Any) -> None:
        """Refuse (``SpecError``) a map whose actuators or links differ from ``head`` (a HeadSpec), by name."""
        head_acts = tuple(head.actuator_names)
        missing = [a for a in head_acts if a not in self._index]
        extra = [a for a in self.actuators if a not in head_acts]
        if missing:
            raise SpecError(self.source, "actuators", f"head {head.name!r} has actuator(s) the link map lacks: "
                            f"{', '.join(missing)}", list(self.actuators))
        if extra:
            raise SpecError(self.source, "actuators", f"link map has actuator(s) not in head {head.name!r}: "
                            f"{', '.join(extra)}", list(head_acts))
        head_links = [link.name for link in head.links]
        missing = [n for n in head_links if n not in self.links]
        extra = [n for n in self.links if n not in head_links]
        if missing:
            raise SpecError(self.source, "links", f"head {head.name!r} has link(s) the link map lacks: "
                            f"{', '.join(missing)}", sorted(self.links))
        if extra:
            raise SpecError(self.source, "links", f"link map has link(s) not in head {head.name!r}: "
                            f"{', '.join(extra)}", head_links)
        for link in head.links:
            fit = self.links[link.name]
            if link.rigid and fit.actuators:
                raise SpecError(self.source, f"links.{link.name}.actuators",
                                "the head declares this link rigid but the map moves it", list(fit.actuators))

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict[str, Any]:
        """The versioned JSON document."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "head": self.head,
            "units": {"actuators": "SI (rad or m)", "position": "m", "rotation": "rad (rotation vector)"},
            "model": "quadratic" if self.degree == 2 else "polynomial",
            "degree": self.degree,
            "actuators": list(self.actuators),
            "neutral": self.neutral.tolist(),
            "scale": self.scale.tolist(),
            "config_units": {k: [u, f] for k, (u, f) in self.units.items()},
            "holdout_rms_mm": self.holdout_rms_mm,
            "links": {
                name: {
                    "actuators": list(f.actuators),
                    "config_actuators": list(f.config_actuators),
                    "selection": f.selection,
                    "rigid": f.rigid,
                    "rotation0": matrix_to_quat(f.rotation0).tolist(),
                    "coefficients": f.coef.tolist(),
                    "samples": f.samples,
                    "rejected": f.rejected,
                    "residual": f.residual,
                    "holdout": f.holdout,
                }
                for name, f in self.links.items()
            },
            "provenance": self.provenance,
        }

    def save(self, path: str | Path) -> Path:
        """Write the map as JSON atomically (:func:`models.atomic.write_text`)."""
        path = Path(path)
        write_text(path, json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n")
        return path

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any], source: str = "<linkmap>") -> LinkMap:
        """Validate a parsed document; errors name the source, key and bad value."""
        if not isinstance(doc, Mapping):
            raise SpecError(source, "document", "must be a JSON object")
        if doc.get("format") != FORMAT:
            raise SpecError(source, "format", f"not a link map (expected {FORMAT!r})", doc.get("format"))
        if doc.get("version") != VERSION:
            raise SpecError(source, "version", f"unsupported version (this build reads {VERSION})", doc.get("version"))
        acts = doc.get("actuators")
        if not isinstance(acts, list) or not all(isinstance(a, str) and a for a in acts) or len(set(acts)) != len(acts):
            raise SpecError(source, "actuators", "must be a list of distinct actuator names", acts)
        neutral = _vector(doc, "neutral", len(acts), source)
        scale = _vector(doc, "scale", len(acts), source)
        if np.any(scale <= 0):
            raise SpecError(source, "scale", "values must be positive", scale.tolist())
        raw_links = doc.get("links")
        if not isinstance(raw_links, Mapping) or not raw_links:
            raise SpecError(source, "links", "must be a non-empty object")
        degree = doc.get("degree", 2)
        if not isinstance(degree, int) or isinstance(degree, bool) or not 2 <= degree <= MAX_DEGREE:
            raise SpecError(source, "degree", f"must be an integer from 2 to {MAX_DEGREE}", degree)
        links = {}
        for name, raw in raw_links.items():
            key = f"links.{name}"
            if not isinstance(raw, Mapping):
                raise SpecError(source, key, "must be an object")
            la = raw.get("actuators", [])
            if not isinstance(la, list) or any(a not in acts for a in la) or len(set(la)) != len(la):
                raise SpecError(source, f"{key}.actuators", "must list distinct actuators of the map", la)
            try:
                coef = np.asarray(raw.get("coefficients"), dtype=float)
                q = np.asarray(raw.get("rotation0"), dtype=float)
            except (TypeError, ValueError) as exc:
                raise SpecError(source, key, f"coefficients/rotation0 must be numbers: {exc}") from exc
            if coef.shape != (n_features(len(la), degree), 6) or not np.all(np.isfinite(coef)):
                raise SpecError(source, f"{key}.coefficients",
                                f"must be {n_features(len(la), degree)}x6 finite numbers", list(coef.shape))
            if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
                raise SpecError(source, f"{key}.rotation0", "must be a quaternion [w, x, y, z]", raw.get("rotation0"))
            links[name] = LinkFit(
                name=name, actuators=tuple(la), coef=coef, rotation0=quat_to_matrix(q),
                rigid=bool(raw.get("rigid", False)), samples=int(raw.get("samples", 0)),
                rejected=int(raw.get("rejected", 0)), residual=dict(raw.get("residual", {})),
                holdout=dict(raw.get("holdout", {})), config_actuators=tuple(raw.get("config_actuators", ())),
                selection=str(raw.get("selection", "data")),
            )
        # the map's own order for each link's actuators
        order = {a: i for i, a in enumerate(acts)}
        for f in links.values():
            if list(f.actuators) != sorted(f.actuators, key=order.__getitem__):
                raise SpecError(source, f"links.{f.name}.actuators", "must follow the map's actuator order",
                                list(f.actuators))
        return cls(acts, neutral, scale, links, head=str(doc.get("head", "")),
                   holdout_rms_mm=doc.get("holdout_rms_mm"), provenance=doc.get("provenance") or {}, source=source,
                   units=_units(doc, acts, source), degree=degree)

    @classmethod
    def load(cls, path: str | Path) -> LinkMap:
        """Read and validate a link map file."""
        path = Path(path)
        return cls.from_dict(load_json(path, "link map"), source=str(path))

    @classmethod
    def for_head(cls, head: Any) -> LinkMap:
        """Load the map named by the head's ``[paths] linkmap`` and check it against the head."""
        path = head.path("linkmap")
        if path is None:
            raise SpecError(str(head.source), "paths.linkmap", "the head config names no link map")
        lm = cls.load(path)
        lm.check_against(head)
        return lm


def _units(doc: Mapping[str, Any], acts: Sequence[str], source: str) -> dict[str, tuple[str, float]]:
    raw = doc.get("config_units") or {}
    if not isinstance(raw, Mapping):
        raise SpecError(source, "config_units", "must map actuator names to [unit, factor to SI]", raw)
    out = {}
    for name, pair in raw.items():
        ok = isinstance(pair, list) and len(pair) == 2 and isinstance(pair[0], str)
        ok = ok and isinstance(pair[1], (int, float)) and math.isfinite(pair[1]) and pair[1] > 0
        if name not in acts or not ok:
            raise SpecError(source, f"config_units.{name}", "must be [unit, positive factor] of a map actuator", pair)
        out[name] = (pair[0], float(pair[1]))
    return out


def _vector(doc: Mapping[str, Any], key: str, n: int, source: str) -> np.ndarray:
    raw = doc.get(key)
    try:
        v = np.asarray(raw, dtype=float)
    except (TypeError, ValueError) as exc:
        raise SpecError(source, key, "must be a list of numbers", raw) from exc
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise SpecError(source, key, f"must list {n} finite numbers (one per actuator)", raw)
    return v




# ---------------------------------------------------------------------------- fitting
@dataclass
class LinkObservations:
    """Observed poses of one link at ``n`` actuator samples; rows with ``valid == False`` are missing."""

    positions: np.ndarray  # (n, 3) m
    quaternions: np.ndarray  # (n, 4) w, x, y, z
    valid: np.ndarray  # (n,) bool

    def rotations(self) -> np.ndarray:
        """Rotation matrices ``(n, 3, 3)`` (identity where invalid)."""
        q = np.where(self.valid[:, None], self.quaternions, np.array([1.0, 0, 0, 0]))
        return quat_to_matrix(q)


@dataclass
class FitOptions:
    """Tuning of :func:`fit_linkmap`.

    An actuator moves a link when its fitted effect over the samples exceeds the absolute thresholds and
    a partial F-test of its terms gives ``p < p_value``. Samples with a residual above ``reject_sigmas`` robust sigmas
    (1.4826·MAD, floored at ``reject_floor_m``) are dropped and the fit repeated.
    """

    move_threshold_m: float = 0.5e-3
    move_threshold_rad: float = math.radians(0.5)
    p_value: float = 1e-6
    min_detection_dof: int = 20  # fewer spare samples than this: trust the head config's actuators instead
    reject_sigmas: float = 5.0
    reject_floor_m: float = 0.3e-3
    reject_floor_rad: float = math.radians(0.3)
    neutral_tolerance: float = 0.02


def _mean_rotation(R: np.ndarray) -> np.ndarray:
    q = matrix_to_quat(R)
    q = np.where((q @ q[0])[:, None] < 0, -q, q)
    return quat_to_matrix(q.mean(axis=0))


def _relative_rotvecs(R: np.ndarray, R0: np.ndarray) -> np.ndarray:
    return matrix_to_rotvec(R @ R0.T)


def _errors(pred: np.ndarray, R0: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> dict[str, float]:
    """rms/max position error (mm) and rms/max angle error (deg) of predictions ``(n, 6)``."""
    dp = np.linalg.norm(pred[:, :3] - pos, axis=1)
    Rp = rotvec_to_matrix(pred[:, 3:]) @ R0
    ang = rotation_angle(np.swapaxes(Rp, 1, 2) @ rot)
    return {
        "rms_mm": float(np.sqrt(np.mean(dp**2)) * 1e3),
        "max_mm": float(dp.max() * 1e3),
        "rms_deg": float(np.degrees(np.sqrt(np.mean(ang**2)))),
        "max_deg": float(np.degrees(ang.max())),
        "samples": int(dp.size),
    }


def _lstsq(Phi: np.ndarray, Y: np.ndarray) -> np.ndarray:
    coef, *_ = np.linalg.lstsq(Phi, Y, rcond=None)
    return coef


def _detect_features(X: np.ndarray, full: bool) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    """Detection design: full quadratic (``full``) or separable ``[1, x_j, x_j^2]``, with each column's actuators."""
    n, A = X.shape
    cols = [np.ones(n)]
    terms: list[tuple[int, ...]] = [()]
    for j in range(A):
        cols.append(X[:, j])
        terms.append((j,))
    for i in range(A):
        for j in range(i, A):
            if i == j or full:
                cols.append(X[:, i] * X[:, j])
                terms.append((i, j))
    return np.stack(cols, axis=1), terms


def _collinear_clusters(X: np.ndarray, tol: float = 1e-9) -> list[list[int]]:
    """Group actuators whose sample columns are proportional (|correlation| = 1): the data cannot tell them apart."""
    A = X.shape[1]
    Xc = X - X.mean(axis=0)
    norms = np.linalg.norm(Xc, axis=0)
    clusters: list[list[int]] = []
    seen: set[int] = set()
    for j in range(A):
        if j in seen:
            continue
        cl = [j]
        for k in range(j + 1, A):
            if k in seen or norms[j] == 0 or norms[k] == 0:
                continue
            if abs(Xc[:, j] @ Xc[:, k]) >= (1 - tol) * norms[j] * norms[k]:
                cl.append(k)
                seen.add(k)
        clusters.append(cl)
    return clusters


def _pick(cluster: list[int], hint: np.ndarray | None) -> list[int]:
    """Of actuators the data cannot separate, those the head config lists for the link (else the first)."""
    if hint is not None:
        listed = [j for j in cluster if hint[j]]
        if listed:
            return listed
    return [cluster[0]]


def _detect(
    X: np.ndarray, Y: np.ndarray, opts: FitOptions, hint: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """Which actuators move a link, from the data.

    Fits a quadratic over all actuators (with cross terms when the samples allow, else separable), then
    keeps actuator ``j`` when the terms involving ``j`` both change the pose by more than the absolute
    thresholds over the samples and are significant by a partial F-test (``p < opts.p_value``) in at
    least one output. Actuators that always moved in proportion in the data are tested together, and the
    ones the head config lists (``hint``) are kept. Returns (moves: bool (A,), effect (A, 2): position m /
    rotation rad) or None when there are too few samples even for the separable design
    (``opts.min_detection_dof`` spare samples).
    """
    from scipy.special import fdtrc

    n, A = X.shape
    full = n >= n_features(A) + opts.min_detection_dof
    if not full and n < 1 + 2 * A + opts.min_detection_dof:
        return None
    Phi, terms = _detect_features(X, full)
    F = Phi.shape[1]
    coef = _lstsq(Phi, Y)
    rss_full = ((Y - Phi @ coef) ** 2).sum(axis=0)
    dof = n - F
    moves = np.zeros(A, dtype=bool)
    effect = np.zeros((A, 2))
    for cluster in _collinear_clusters(X):
        # actuators that always moved together in this data (e.g. a "together" group) are tested as one
        mask = np.array([any(j in t for j in cluster) for t in terms])
        contrib = Phi[:, mask] @ coef[mask]
        contrib = contrib - contrib.mean(axis=0)
        pos_eff = np.linalg.norm(contrib[:, :3], axis=1).max()
        rot_eff = np.linalg.norm(contrib[:, 3:], axis=1).max()
        effect[cluster] = (pos_eff, rot_eff)
        if pos_eff <= opts.move_threshold_m and rot_eff <= opts.move_threshold_rad:
            continue
        reduced = Phi[:, ~mask]
        rss_red = ((Y - reduced @ _lstsq(reduced, Y)) ** 2).sum(axis=0)
        q = int(np.linalg.matrix_rank(Phi[:, mask]))
        with np.errstate(divide="ignore", invalid="ignore"):
            stat = ((rss_red - rss_full) / q) / np.maximum(rss_full / dof, 1e-300)
        pval = fdtrc(q, dof, np.nan_to_num(stat, nan=0.0, posinf=1e300))
        pos_sig = pos_eff > opts.move_threshold_m and np.any(pval[:3] < opts.p_value)
        rot_sig = rot_eff > opts.move_threshold_rad and np.any(pval[3:] < opts.p_value)
        if pos_sig or rot_sig:
            moves[_pick(cluster, hint)] = True
    return moves, effect


def _fit_link(
    X: np.ndarray, Y: np.ndarray, opts: FitOptions, degree: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Robust polynomial LSQ: fit, drop samples beyond ``reject_sigmas`` robust sigmas, refit. Returns coef, kept."""
    Phi = quad_features(X, degree)
    keep = np.ones(len(X), dtype=bool)
    coef = _lstsq(Phi, Y)
    for _ in range(3):
        r = Y - Phi @ coef
        ep = np.linalg.norm(r[:, :3], axis=1)
        er = np.linalg.norm(r[:, 3:], axis=1)
        sp = max(1.4826 * np.median(ep[keep]), opts.reject_floor_m / opts.reject_sigmas)
        sr = max(1.4826 * np.median(er[keep]), opts.reject_floor_rad / opts.reject_sigmas)
        new_keep = (ep <= opts.reject_sigmas * sp) & (er <= opts.reject_sigmas * sr)
        if new_keep.sum() < Phi.shape[1] + 1 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
        coef = _lstsq(Phi[keep], Y[keep])
    return coef, keep


def fit_linkmap(
    actuators: Sequence[str],
    neutral: Sequence[float],
    scale: Sequence[float],
    P: np.ndarray,
    observations: Mapping[str, LinkObservations],
    *,
    config_links: Mapping[str, Sequence[str]] | None = None,
    rigid: Sequence[str] = (),
    head: str = "",
    provenance: Mapping[str, Any] | None = None,
    options: FitOptions | None = None,
    units: Mapping[str, tuple[str, float]] | None = None,
    degree: int = 2,
) -> LinkMap:
    """Fit m(p) from actuator samples ``P`` ``(n, A)`` (SI) and per-link observed poses.

    The actuators that move each link are detected from the data when there are enough samples
    (otherwise the head config's ``config_links`` are used); rigid links get a constant pose.
    """
    opts = options or FitOptions()
    actuators = tuple(actuators)
    neutral = np.asarray(neutral, dtype=float)
    scale = np.asarray(scale, dtype=float)
    P = np.atleast_2d(np.asarray(P, dtype=float))
    if P.shape[1] != len(actuators):
        raise ValueError(f"samples have {P.shape[1]} columns, expected {len(actuators)} actuators")
    X = (P - neutral) / scale
    config_links = dict(config_links or {})
    links: dict[str, LinkFit] = {}
    for name, obs in observations.items():
        ok = np.asarray(obs.valid, dtype=bool)
        if ok.sum() == 0:
            raise ValueError(f"link {name!r}: no valid observations")
        Xl = X[ok]
        pos = obs.positions[ok]
        R = obs.rotations()[ok]
        near = np.max(np.abs(Xl), axis=1) <= opts.neutral_tolerance
        R0 = _mean_rotation(R[near]) if near.any() else R[np.argmin(np.linalg.norm(Xl, axis=1))]
        Y = np.concatenate([pos, _relative_rotvecs(R, R0)], axis=1)
        cfg = tuple(config_links.get(name, ()))
        if name in rigid:
            sel = np.zeros(len(actuators), dtype=bool)
            selection = "rigid"
        else:
            det = _detect(Xl, Y, opts, hint=np.array([a in cfg for a in actuators]))
            if det is None:
                sel = np.array([a in cfg for a in actuators])
                selection = "config"
            else:
                sel = det[0]
                selection = "data"
        idx = np.flatnonzero(sel)
        if ok.sum() < n_features(idx.size, degree) + 1:
            raise ValueError(
                f"link {name!r}: {ok.sum()} valid samples cannot fit a quadratic in {idx.size} actuators "
                f"(need more than {n_features(idx.size, degree)})"
            )
        coef, keep = _fit_link(Xl[:, idx], Y, opts, degree)
        fit = LinkFit(
            name=name, actuators=tuple(actuators[i] for i in idx), coef=coef, rotation0=R0, rigid=name in rigid,
            samples=int(keep.sum()), rejected=int((~keep).sum()), config_actuators=cfg, selection=selection,
        )
        pred = quad_features(Xl[:, idx][keep], degree) @ coef
        fit.residual = _errors(pred, R0, pos[keep], R[keep])
        links[name] = fit
    return LinkMap(actuators, neutral, scale, links, head=head, provenance=provenance, units=units, degree=degree)
