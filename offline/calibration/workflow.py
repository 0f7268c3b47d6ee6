"""The calibration run: discover limits, plan, drive and record (resumably), fit m(p), validate, write outputs.

Outputs in the run directory: ``journal.jsonl`` (every recorded pose; resuming skips them), ``plan.json``,
``discovery.json`` (travel limits), ``capture.csv`` (every tracker sample received, in the capture export
format), ``linkmap.json``, ``report.json``, ``report.png`` and ``proposed_config.toml``. All files except the
append-only journal and capture log are written atomically.

A live run drives a :class:`~offline.calibration.heads.HeadDriver` and reads a tracker source; a replay run
(``calibrate_replay``) refits from a recorded capture CSV and the journal of the run that drove the head,
so recorded capture data gives the same fit as the live stream did.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_text
from models.capture import MarkerSample
from models.headspec import HeadSpec
from models.linkmap import LinkMap, LinkObservations, fit_linkmap
from offline.calibration.capture import CalibrationError, LinkEstimate, TrackerSource, estimate
from offline.calibration.discovery import LimitResult, discover_limits, proposed_config, zero_offsets
from offline.calibration.heads import HeadDriver
from offline.calibration.journal import Journal
from offline.calibration.plan import Plan, make_plan
from offline.calibration.report import write_plot, write_report

#: One pose's capture: ``n`` frames' samples and each link's estimate from them.
Collect = Callable[[int], tuple[list[MarkerSample], dict[str, LinkEstimate]]]


@dataclass
class CalibrationSettings:
    """Knobs of a run (SI where physical)."""

    samples: int = 120
    seed: int = 0
    sweep_levels: int = 5
    holdout_fraction: float = 0.25
    frames_per_pose: int = 8
    discover: bool = True
    discover_actuators: Sequence[str] | None = None
    discover_step: float = math.radians(3.0)
    progress: bool = True
    tracker: str = ""
    tie_groups: bool = False  # move together/mirror groups as one (the daemon enforces them)
    driver: str = ""  # how the head was driven: hardware, daemon ENDPOINT, ideal-motors (provenance)
    #: quadratic: the free quadratic map; auto: also fit the head's mechanism file, keep the smaller hold-out error;
    #: mechanism: the fitted mechanism's map whatever the errors (offline/calibration/mechanism_fit.py).
    link_model: str = "quadratic"
    fit_joints: bool = False  # mechanism fit: joint positions too, besides zero offsets and rod lengths


@dataclass
class CalibrationResult:
    """What a run produced."""

    linkmap: LinkMap
    report: dict[str, Any]
    out_dir: Path
    poses_recorded: int  # poses driven and recorded in this run (not counting resumed ones)
    limits: dict[str, LimitResult] = field(default_factory=dict)
    offsets: dict[str, float] = field(default_factory=dict)


class Progress:
    """A one-line text progress bar on stderr."""

    def __init__(self, total: int, enabled: bool, label: str = "calibrate") -> None:
        self.total = max(total, 1)
        self.enabled = enabled
        self.label = label
        self.t0 = time.monotonic()

    def update(self, done: int, note: str = "") -> None:
        if not self.enabled:
            return
        frac = min(done / self.total, 1.0)
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        rate = done / max(time.monotonic() - self.t0, 1e-9)
        sys.stderr.write(f"\r{self.label} [{bar}] {done}/{self.total} {rate:5.1f}/s {note[:40]:<40}")
        sys.stderr.flush()

    def message(self, note: str) -> None:
        if self.enabled:
            sys.stderr.write(f"\r{self.label}: {note[:100]:<100}")
            sys.stderr.flush()

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


def _link_names(head: HeadSpec) -> list[str]:
    return [link.name for link in head.links]


# ---------------------------------------------------------------------------- live run
def calibrate_live(
    head: HeadSpec,
    driver: HeadDriver,
    source: TrackerSource,
    out_dir: str | Path,
    settings: CalibrationSettings | None = None,
    reference: Mapping[str, np.ndarray] | None = None,
) -> CalibrationResult:
    """Drive ``driver`` through the plan, reading ``source``; resume from ``out_dir``'s journal if present."""
    from models.capture import CsvAppender

    s = settings or CalibrationSettings()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    links = _link_names(head)
    capture = CsvAppender(out / "capture.csv")
    journal = Journal(out / "journal.jsonl").load()

    def collect(n: int) -> tuple[list[MarkerSample], dict[str, LinkEstimate]]:
        samples = list(source.collect(n))
        capture.write(samples)
        return samples, estimate(samples, links, n)

    try:
        limits = _discovery(head, driver, collect, out, s)
        plan = _plan(head, s, limits, out)
        journal.start(_header(head, plan, s))
        todo = [p for p in plan.poses if p.index not in journal.poses]
        bar = Progress(len(plan.poses), s.progress)
        recorded = 0
        done = len(plan.poses) - len(todo)
        for pose in todo:
            driver.move_to(pose.values)
            driver.wait_settled()
            measured = driver.measured()
            samples, est = collect(s.frames_per_pose)
            times = [x.time for x in samples]
            journal.append({
                "type": "pose", "index": pose.index, "kind": pose.kind, "holdout": pose.holdout,
                "commanded": _commanded(driver, pose.values), "measured": measured,
                "t0": min(times) if times else None, "t1": max(times) if times else None,
                "links": {n: e.to_json() for n, e in est.items()},
            })
            recorded += 1
            done += 1
            bar.update(done, pose.kind)
        driver.move_to({a.name: a.neutral for a in head.actuators})
        bar.done()
    finally:
        journal.close()
        capture.close()
    records = [journal.poses[p.index] for p in plan.poses]
    return _finish(head, plan, records, out, s, limits, reference, recorded)


def _discovery(head: HeadSpec, driver: HeadDriver, collect: Collect, out: Path,
               s: CalibrationSettings) -> dict[str, LimitResult]:
    path = out / "discovery.json"
    if path.exists():
        doc = json.loads(path.read_text(encoding="utf-8"))
        return {n: LimitResult.from_json(n, d) for n, d in doc["limits"].items()}
    if not s.discover:
        return {}
    bar = Progress(0, s.progress, "discovery")
    frames = max(2, s.frames_per_pose // 2)

    def observe() -> dict[str, np.ndarray]:
        _, est = collect(frames)
        return {n: e.position for n, e in est.items()}

    res = discover_limits(head, driver, observe, actuators=s.discover_actuators, step=s.discover_step,
                          progress=bar.message)
    bar.done()
    write_text(path, json.dumps({"limits": {n: r.to_json() for n, r in res.items()}}, indent=1) + "\n")
    return res


def _plan(head: HeadSpec, s: CalibrationSettings, limits: Mapping[str, LimitResult], out: Path) -> Plan:
    plan = make_plan(head, samples=s.samples, seed=s.seed, sweep_levels=s.sweep_levels,
                     holdout_fraction=s.holdout_fraction, limits={n: r.proposed for n, r in limits.items()},
                     tie_groups=s.tie_groups)
    write_text(out / "plan.json", json.dumps({"digest": plan.digest(), **plan.to_dict()}) + "\n")
    return plan


def _header(head: HeadSpec, plan: Plan, s: CalibrationSettings) -> dict[str, Any]:
    return {"plan": plan.digest(), "head": head.name, "actuators": list(head.actuator_names),
            "frames_per_pose": s.frames_per_pose, "tracker": s.tracker}


# ---------------------------------------------------------------------------- replay
def calibrate_replay(
    head: HeadSpec,
    capture_csv: str | Path,
    journal_path: str | Path,
    out_dir: str | Path,
    settings: CalibrationSettings | None = None,
    reference: Mapping[str, np.ndarray] | None = None,
) -> CalibrationResult:
    """Refit from a capture export: each journal pose's window ``[t0, t1]`` selects its samples."""
    from models.capture import CaptureLog, read_csv

    s = settings or CalibrationSettings()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    journal = Journal(journal_path).load()
    if journal.header is None or not journal.poses:
        raise CalibrationError(f"{journal_path}: no recorded poses to replay")
    if journal.header.get("actuators") != list(head.actuator_names):
        raise CalibrationError(f"{journal_path}: recorded for actuators {journal.header.get('actuators')}, "
                               f"but head {head.name!r} has {list(head.actuator_names)}")
    log = CaptureLog(read_csv(capture_csv))
    frames = int(journal.header.get("frames_per_pose", s.frames_per_pose))
    links = _link_names(head)
    records = []
    for idx in sorted(journal.poses):
        rec = dict(journal.poses[idx])
        if rec.get("t0") is None:
            rec["links"] = {}
        else:
            est = estimate(log.between(rec["t0"], rec["t1"]), links, frames)
            rec["links"] = {n: e.to_json() for n, e in est.items()}
        records.append(rec)
    disc = Path(journal_path).parent / "discovery.json"
    limits = {}
    if disc.exists():
        doc = json.loads(disc.read_text(encoding="utf-8"))
        limits = {n: LimitResult.from_json(n, d) for n, d in doc["limits"].items()}
    s.tracker = s.tracker or str(capture_csv)
    plan = Plan(tuple(head.actuator_names), (), s.seed)
    return _finish(head, plan, records, out, s, limits, reference, 0, plan_digest=journal.header.get("plan"))


# ---------------------------------------------------------------------------- fit and report
def dataset(head: HeadSpec, records: Sequence[Mapping[str, Any]]
            ) -> tuple[np.ndarray, dict[str, LinkObservations], np.ndarray]:
    """Measured actuator matrix ``(n, A)``, per-link observations and the hold-out mask from pose records."""
    names = list(head.actuator_names)
    n = len(records)
    P = np.array([[float(r["measured"][a]) for a in names] for r in records]) if n else np.zeros((0, len(names)))
    obs = {}
    for link in _link_names(head):
        pos = np.zeros((n, 3))
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        valid = np.zeros(n, dtype=bool)
        for i, r in enumerate(records):
            e = r["links"].get(link)
            if e is not None:
                pos[i] = e["p"]
                quat[i] = e["q"]
                valid[i] = True
        obs[link] = LinkObservations(pos, quat, valid)
    holdout = np.array([bool(r.get("holdout")) for r in records], dtype=bool)
    return P, obs, holdout


def _subset(obs: Mapping[str, LinkObservations], mask: np.ndarray) -> dict[str, LinkObservations]:
    return {n: LinkObservations(o.positions[mask], o.quaternions[mask], o.valid[mask]) for n, o in obs.items()}


def noise_floor_mm(records: Sequence[Mapping[str, Any]], links: Sequence[str]) -> float | None:
    """3-D RMS scatter (mm) of link positions over the repeated neutral poses: the per-pose noise floor."""
    sq = []
    for link in links:
        ps = np.array([r["links"][link]["p"] for r in records if r.get("kind") == "neutral" and link in r["links"]])
        if len(ps) >= 2:
            d = ps - ps.mean(axis=0)
            sq.append(((d**2).sum(axis=1).sum() / (len(ps) - 1), len(ps)))
    if not sq:
        return None
    return float(math.sqrt(sum(v for v, _ in sq) / len(sq)) * 1e3)


def _finish(
    head: HeadSpec, plan: Plan, records: list[dict[str, Any]], out: Path, s: CalibrationSettings,
    limits: Mapping[str, LimitResult],
    reference: Mapping[str, np.ndarray] | None, recorded: int, plan_digest: str | None = None,
) -> CalibrationResult:
    P, obs, holdout = dataset(head, records)
    fit_mask = ~holdout
    neutral = np.array(head.neutral_pose)
    scale = np.array([(a.max - a.min) / 2 for a in head.actuators])
    provenance = {
        "created": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "tool": "likeness calibrate",
        "head": head.name,
        "head_config": str(head.source),
        "head_config_sha256": _sha256(head.source),
        "tracker": s.tracker,
        "driver": s.driver,
        "seed": s.seed,
        "plan": plan_digest or plan.digest(),
        "poses": len(records),
        "fit_poses": int(fit_mask.sum()),
        "holdout_poses": int(holdout.sum()),
        "frames_per_pose": s.frames_per_pose,
    }
    lm = fit_linkmap(
        head.actuator_names, neutral, scale, P[fit_mask], _subset(obs, fit_mask),
        config_links={link.name: link.actuators for link in head.links},
        rigid=[link.name for link in head.links if link.rigid], head=head.name, provenance=provenance,
        units={a.name: (a.unit, a.unit_scale) for a in head.actuators},
    )
    models: dict[str, Any] = {"chosen": "quadratic"}
    if s.link_model != "quadratic" and head.path("mechanism") is not None:
        from offline.calibration.mechanism_fit import choose_link_map

        lm, models = choose_link_map(head, lm, P, obs, fit_mask, holdout, s.link_model, s.fit_joints)
    per_link: dict[str, dict[str, float]] = {}
    hold_err: dict[str, np.ndarray] = {}
    if holdout.any():
        per_link = lm.evaluate(P[holdout], _subset(obs, holdout))
        pred = lm.predict(P[holdout])
        sq = []
        for name, o in _subset(obs, holdout).items():
            e = np.linalg.norm(pred[name][o.valid, :3] - o.positions[o.valid], axis=1) * 1e3
            hold_err[name] = e
            sq.append(e**2)
        lm.holdout_rms_mm = float(np.sqrt(np.mean(np.concatenate(sq)))) if sq else None
        for name, stats in per_link.items():
            lm.links[name].holdout = stats
    offsets = zero_offsets(head, lm, reference) if reference is not None else {}
    lm.source = str(out / "linkmap.json")
    lm.save(out / "linkmap.json")
    floor = noise_floor_mm(records, _link_names(head))
    report = {
        "links": {n: {k: per_link.get(n, lm.links[n].residual)[k] for k in ("rms_mm", "max_mm", "rms_deg")}
                  for n in lm.links},
        "holdout_rms_mm": lm.holdout_rms_mm,
        "head": head.name,
        "noise_floor_mm": floor,
        "holdout_over_noise": (lm.holdout_rms_mm / floor) if (floor and lm.holdout_rms_mm is not None) else None,
        "holdout": per_link,
        "fit": {n: f.residual for n, f in lm.links.items()},
        "detected_actuators": {n: list(f.actuators) for n, f in lm.links.items()},
        "config_actuators": {link.name: list(link.actuators) for link in head.links},
        "actuator_selection": {n: f.selection for n, f in lm.links.items()},
        "rejected_samples": int(sum(
            e.get("rejected", 0) for r in records for e in r["links"].values()
        )),
        "outlier_poses_rejected": {n: f.rejected for n, f in lm.links.items()},
        "limits": {n: r.to_json() for n, r in limits.items()},
        "zero_offsets_deg": {n: math.degrees(v) for n, v in offsets.items()},
        "provenance": provenance,
        "link_model": models,
    }
    write_report(out / "report.json", report)
    write_plot(out / "report.png", report, hold_err)
    if limits or offsets:
        write_text(out / "proposed_config.toml", proposed_config(head, limits, offsets))
    return CalibrationResult(lm, report, out, recorded, dict(limits), offsets)


def _sha256(path: Path) -> str | None:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def _commanded(driver: HeadDriver, planned: Mapping[str, float]) -> dict[str, float]:
    """What the driver really commanded for a planned pose (a safety stage may stop short of it)."""
    get = getattr(driver, "commanded", None)
    return dict(planned) if get is None else {**planned, **get()}
