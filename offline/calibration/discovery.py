"""Per-actuator travel-limit discovery and zero offsets, and the proposed config change for the operator.

Limits: each actuator sweeps slowly from neutral towards each configured limit (never beyond it) in small
steps while the others hold neutral; the sweep stops when the tracked links stop moving (two steps in a row
with under a fifth of the typical step motion) or the drive reports a fault such as a following error. The
last moving position, less a margin, is the proposed limit; a sweep that reaches the configured limit keeps it.

Zero offsets: with a fitted link map and the links' reference rest poses (the design pose of each attachment,
e.g. the mesh node sets' frames), the actuator values that put every link at rest are found by least squares;
their difference from the configured neutral is each actuator's zero offset.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np

from models.headspec import HeadSpec
from models.linkmap import LinkMap
from models.rigid import matrix_to_rotvec
from offline.calibration.heads import HeadDriver


@dataclass
class LimitResult:
    """What one actuator's sweeps found (SI): proposed ``min``/``max`` and why."""

    name: str
    configured: tuple[float, float]
    proposed: tuple[float, float]
    stop_found: tuple[bool, bool] = (False, False)
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        return {"configured": list(self.configured), "proposed": list(self.proposed),
                "stop_found": list(self.stop_found), "notes": self.notes}

    @classmethod
    def from_json(cls, name: str, d: Mapping) -> LimitResult:
        return cls(name, tuple(d["configured"]), tuple(d["proposed"]), tuple(d["stop_found"]), list(d["notes"]))


def discover_limits(
    head: HeadSpec,
    driver: HeadDriver,
    observe: Callable[[], dict[str, np.ndarray]],
    actuators: Sequence[str] | None = None,
    step: float = math.radians(3.0),
    margin: float = math.radians(1.0),
    stall_fraction: float = 0.2,
    min_motion: float = 0.05e-3,
    progress: Callable[[str], None] | None = None,
) -> dict[str, LimitResult]:
    """Sweep each actuator to both configured limits; ``observe()`` returns link name → position (m).

    Links watched for an actuator are those the head config lists it under (all links if none).
    """
    neutral = {a.name: a.neutral for a in head.actuators}
    names = list(actuators) if actuators is not None else list(head.actuator_names)
    results: dict[str, LimitResult] = {}
    for name in names:
        act = head.actuator(name)
        watch = [link.name for link in head.links if name in link.actuators] or [link.name for link in head.links]
        proposed = [act.min, act.max]
        found = [False, False]
        notes: list[str] = []
        for side, bound in ((0, act.min), (1, act.max)):
            if progress:
                progress(f"{name} towards {math.degrees(bound):+.1f}")
            direction = 1.0 if bound > act.neutral else -1.0
            values = [*np.arange(act.neutral, bound, direction * step)[1:], bound]
            driver.move_to(neutral)
            driver.wait_settled()
            prev = observe()
            motions: list[float] = []
            last_moving = act.neutral
            stalled = 0
            for v in values:
                driver.move_to({**neutral, name: float(v)})
                try:
                    driver.wait_settled()
                except Exception as exc:  # following error / fault: the drive hit something
                    notes.append(f"fault at {math.degrees(v):.1f} deg: {exc}")
                    faults = driver.faults()
                    if faults:
                        notes.append("; ".join(faults))
                    found[side] = True
                    recover = getattr(driver, "recover", None)
                    if recover is None:
                        raise
                    recover()
                    break
                cur = observe()
                common = [k for k in watch if k in cur and k in prev]
                motion = max((float(np.linalg.norm(cur[k] - prev[k])) for k in common), default=0.0)
                typical = float(np.median(motions)) if motions else math.inf
                if len(motions) >= 2 and motion < max(stall_fraction * typical, min_motion):
                    stalled += 1
                    if stalled >= 2:
                        found[side] = True
                        notes.append(f"links stopped moving beyond {math.degrees(last_moving):.1f} deg")
                        break
                else:
                    stalled = 0
                    last_moving = float(v)
                    motions.append(motion)
                prev = cur
            if found[side]:
                proposed[side] = last_moving - direction * margin
        driver.move_to(neutral)
        driver.wait_settled()
        results[name] = LimitResult(name, (act.min, act.max), (proposed[0], proposed[1]), (found[0], found[1]), notes)
    return results


def zero_offsets(head: HeadSpec, linkmap: LinkMap, reference: Mapping[str, np.ndarray],
                 rot_weight_deg: float = 1.0) -> dict[str, float]:
    """Actuator values (minus neutral, SI) that bring the fitted links closest to their reference poses.

    ``reference`` maps link name → 4x4 rest pose in the tracker frame; 1 mm of position counts as much as
    ``rot_weight_deg`` degrees of rotation. Only actuators that move some link get an offset.
    """
    from scipy.optimize import least_squares

    links = [n for n, f in linkmap.links.items() if f.actuators and n in reference]
    used = sorted({a for n in links for a in linkmap.links[n].actuators}, key=linkmap.actuators.index)
    idx = [linkmap.actuators.index(a) for a in used]
    lo = np.array([head.actuator(a).min for a in used])
    hi = np.array([head.actuator(a).max for a in used])
    t_ref = {n: reference[n][:3, 3] for n in links}
    r_ref = {n: matrix_to_rotvec(reference[n][:3, :3] @ linkmap.links[n].rotation0.T) for n in links}
    w_rot = 1.0 / math.radians(rot_weight_deg)

    def residual(x: np.ndarray) -> np.ndarray:
        p = linkmap.neutral.copy()
        p[idx] = x
        pred = linkmap.predict(p[None, :])
        out = []
        for n in links:
            y = pred[n][0]
            out.append((y[:3] - t_ref[n]) * 1e3)
            out.append((y[3:] - r_ref[n]) * w_rot)
        return np.concatenate(out)

    x0 = linkmap.neutral[idx]
    sol = least_squares(residual, x0, bounds=(lo, hi))
    return {a: float(sol.x[i] - head.actuator(a).neutral) for i, a in enumerate(used)}


def proposed_config(head: HeadSpec, limits: Mapping[str, LimitResult], offsets: Mapping[str, float]) -> str:
    """A TOML snippet of ``[[actuators]]`` changes (config units) for the operator to review and merge."""
    when = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    lines = [
        f"# Proposed by `likeness calibrate` for head {head.name!r} on {when}.",
        f"# Review, then merge into {head.source} by hand: nothing has been changed automatically.",
        "# zero_count: encoder count at output position 0, shifted so that 0 is where the link sits at rest.",
        "",
    ]
    for a in head.actuators:
        lim = limits.get(a.name)
        off = offsets.get(a.name)
        if lim is None and off is None:
            continue
        lines.append("[[actuators]]")
        lines.append(f'name = "{a.name}"')
        if lim is not None:
            for side, key in ((0, "min"), (1, "max")):
                old = a.to_config_units(lim.configured[side])
                new = a.to_config_units(lim.proposed[side])
                why = "stop found" if lim.stop_found[side] else "no stop within configured travel"
                change = f"was {old:.2f}" if abs(new - old) > 1e-9 else "unchanged"
                lines.append(f"{key} = {new:.2f}  # {change}; {why}")
        if off is not None:
            cpu = a.direction * a.counts_per_rev * a.gear_ratio / (2 * math.pi) if a.kind == "rotary" else None
            off_cfg = a.to_config_units(off)
            if cpu is not None:
                new_zero = a.zero_count + round(off * cpu)
                lines.append(f"zero_count = {new_zero}  # was {a.zero_count}; zero offset {off_cfg:+.3f} {a.unit}")
            else:
                lines.append(f"# zero offset {off_cfg:+.3f} {a.unit}: shift zero_count by {off_cfg:+.3f} {a.unit}")
        lines.append("")
    return "\n".join(lines)
