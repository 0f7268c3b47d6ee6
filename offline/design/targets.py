"""Target expressions for face cloning: face-unit weights → target outer surfaces.

A target is a name and a map of face units (the 52 ARKit-named units of the skin's ``face_units.npz``) to weights;
its surface is the rest outer surface plus Σ wᵢ Δᵢ. ``--targets FILE`` is JSON of the same shape:
``{"target name": {"faceUnit": weight, ...}, ...}``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from models.errors import SpecError

#: The default expressive set: a strong jaw opening, each one-sided smile, a full smile, surprise, anger, a blink,
#: an "ah" vowel and a sneer-like upper-lip raise. Weights stay at or below 1 (the units' captured range).
DEFAULT_TARGETS: dict[str, dict[str, float]] = {
    "jaw_open": {"jawOpen": 1.0},
    "smile_left": {"mouthSmileLeft": 1.0, "cheekSquintLeft": 0.5},
    "smile_right": {"mouthSmileRight": 1.0, "cheekSquintRight": 0.5},
    "smile_open": {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.8, "cheekSquintLeft": 0.4, "cheekSquintRight": 0.4,
                   "jawOpen": 0.25},
    "surprise": {"browInnerUp": 0.8, "browOuterUpLeft": 0.8, "browOuterUpRight": 0.8, "eyeWideLeft": 0.5,
                 "eyeWideRight": 0.5, "jawOpen": 0.35},
    "anger": {"browDownLeft": 0.8, "browDownRight": 0.8, "mouthFrownLeft": 0.6, "mouthFrownRight": 0.6,
              "noseSneerLeft": 0.3, "noseSneerRight": 0.3},
    "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
    "vowel_ah": {"jawOpen": 0.55, "mouthStretchLeft": 0.3, "mouthStretchRight": 0.3, "mouthUpperUpLeft": 0.2,
                 "mouthUpperUpRight": 0.2},
    "upper_lip_raise": {"mouthUpperUpLeft": 0.8, "mouthUpperUpRight": 0.8, "mouthShrugUpper": 0.3},
}


def check_targets(targets: Mapping[str, Mapping[str, float]], units: Sequence[str], source: str) -> dict:
    """The targets as plain dicts, or a :class:`SpecError` naming the target and unit that are wrong."""
    if not isinstance(targets, Mapping) or not targets:
        raise SpecError(source, "targets", "must be a non-empty JSON object {name: {faceUnit: weight}}")
    known = set(units)
    out: dict[str, dict[str, float]] = {}
    for name, weights in targets.items():
        if not isinstance(name, str) or not name:
            raise SpecError(source, "targets", "target names must be non-empty strings", name)
        if not isinstance(weights, Mapping) or not weights:
            raise SpecError(source, f"targets.{name}", "must be a non-empty object {faceUnit: weight}", weights)
        clean = {}
        for unit, w in weights.items():
            if unit not in known:
                raise SpecError(source, f"targets.{name}.{unit}",
                                f"unknown face unit; known: {', '.join(sorted(known))}")
            if isinstance(w, bool) or not isinstance(w, int | float) or not np.isfinite(w) or not -2 <= w <= 2:
                raise SpecError(source, f"targets.{name}.{unit}", "weight must be a number in [-2, 2]", w)
            clean[unit] = float(w)
        out[name] = clean
    return out


def load_targets(path: str | Path, units: Sequence[str]) -> dict[str, dict[str, float]]:
    """Targets from a JSON file (see the module docstring)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SpecError(str(path), "file", f"cannot read targets: {exc}") from exc
    return check_targets(doc, units, str(path))


def unit_weights(weights: Mapping[str, float], units: Sequence[str]) -> np.ndarray:
    """The weight vector (U,) in ``units`` order."""
    index = {u: i for i, u in enumerate(units)}
    w = np.zeros(len(units))
    for u, v in weights.items():
        w[index[u]] = v
    return w


def target_surface(rest: np.ndarray, offsets: np.ndarray, units: Sequence[str], weights: Mapping[str, float]
                   ) -> np.ndarray:
    """Target outer surface (V, 3): ``rest`` + Σ wᵢ ``offsets``[i]."""
    w = unit_weights(weights, units)
    return np.asarray(rest, dtype=np.float64) + np.tensordot(w, np.asarray(offsets, dtype=np.float64), axes=1)
