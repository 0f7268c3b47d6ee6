"""The soak's figures against its goals, its printed summary and its timeline picture (matplotlib)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

#: Goals: missed deadlines outside fault handling, frames lost, memory growth of the daemon's processes.
GOAL_MISSED = 0
GOAL_LOST = 0
GOAL_GROWTH_MIB = 10.0


def _fault_windows(raw: dict[str, Any], settle_s: float, interval: float) -> list[tuple[float, float]]:
    """From each injection to ``settle_s`` after the head was active again (or to the next slot if it never was)."""
    out = []
    for run in raw["runs"]:
        end = run.t_recovered + settle_s if run.t_recovered is not None else run.t_inject + interval
        out.append((run.t_inject - 0.2, end))
    return out


def _missed(states: list[tuple], windows: list[tuple[float, float]], t_from: float, t_to: float) -> dict[str, int]:
    """Deadlines missed between ``t_from`` and ``t_to`` (from the loop's counter in the state telemetry), split into
    inside and outside the fault windows."""
    inside = outside = 0
    prev = None
    for t, _cycles, missed, *_ in states:
        if prev is not None and t_from <= t <= t_to:
            step = missed - prev[1]
            if step > 0:
                if any(a <= t and prev[0] <= b for a, b in windows):
                    inside += step
                else:
                    outside += step
        prev = (t, missed)
    return {"outside_fault_handling": outside, "during_fault_handling": inside}


def _covered(points: list[float], near_s: float, windows: list[tuple[float, float]], t_from: float,
             t_to: float) -> float:
    """Share of the time from ``t_from`` to ``t_to`` outside ``windows`` that lies within ``near_s`` of a point:
    the chance that a moment picked at random there comes "near" one by coincidence."""
    import numpy as np

    if t_to <= t_from:
        return 0.0
    grid = np.linspace(t_from, t_to, max(2, int((t_to - t_from) / 1e-3)))
    keep = np.ones(len(grid), bool)
    for a, b in windows:
        keep &= ~((grid >= a) & (grid <= b))
    if not keep.any():
        return 0.0
    pts = np.sort(np.asarray(points, float))
    if not len(pts):
        return 0.0
    g = grid[keep]
    i = np.clip(np.searchsorted(pts, g), 1, len(pts) - 1) if len(pts) > 1 else np.zeros(len(g), int)
    dist = np.minimum(np.abs(g - pts[i]), np.abs(g - pts[np.maximum(i - 1, 0)]))
    return float(np.mean(dist <= near_s))


def _machine_stalls(states: list[tuple], windows: list[tuple[float, float]], t_from: float, t_to: float,
                    sentinel: dict[str, Any], near_s: float = 0.05,
                    records: list[tuple[float, int]] | None = None) -> dict[str, Any]:
    """The bare realtime loop's misses between ``t_from`` and ``t_to`` (:mod:`benchmarks._soak_sentinel`) and its
    slow wake-ups, outside the fault windows, and how many of the daemon's misses outside them came within ``near_s``
    of a miss, and of a miss or a slow wake-up, with the chance of that by coincidence (the share of the time within
    ``near_s`` of one).

    ``records``: the daemon's misses at their own times ((t, deadlines), the loop's ``deadline_miss`` causes). Without
    them each miss is placed between the two state messages whose counters differ, which trail the miss by up to
    the loop's statistics period (0.5 s): too late to match a sign of the host 50 ms away."""
    misses = [(t, n, late) for t, n, late in sentinel.get("misses", []) if t_from <= t <= t_to]
    slow = [t for t, _ in sentinel.get("slow", []) if t_from <= t <= t_to]
    def outside(t0: float, t1: float) -> bool:
        return not any(a <= t1 and t0 <= b for a, b in windows)
    own = sum(n for t, n, _ in misses if outside(t, t))
    spans: list[tuple[float, float, int]] = []
    if records is not None:
        spans = [(t, t, n) for t, n in records if t_from <= t <= t_to and outside(t, t)]
    else:
        prev = None
        for t, _cycles, missed, *_ in states:
            if prev is not None and t_from <= t <= t_to and (step := missed - prev[1]) > 0 and outside(prev[0], t):
                spans.append((prev[0], t, step))
            prev = (t, missed)
    daemon = shared = with_slow = 0
    for t0, t1, step in spans:
        daemon += step
        near_miss = any(t0 - near_s <= ts <= t1 + near_s for ts, _, _ in misses)
        if near_miss:
            shared += step
        if near_miss or any(t0 - near_s <= ts <= t1 + near_s for ts in slow):
            with_slow += step
    return {"scheduling": sentinel.get("scheduling", ""), "missed_outside_fault_handling": own,
            "worst_lateness_ms": round(max((late for _, _, late in misses), default=0.0) * 1e3, 2),
            "slow_wakeups_outside_fault_handling": sum(1 for t in slow if outside(t, t)),
            "probe_median_us": [round(m * 1e6, 1) for m in sentinel.get("probe_median", [])],
            "slow_factor": sentinel.get("slow_factor"),
            "daemon_misses_outside": daemon, "daemon_misses_with_one": shared,
            "daemon_misses_with_a_miss_or_slow_wakeup": with_slow,
            "matched_by": "the loop's own miss times" if records is not None else "state messages (late by <= 0.5 s)",
            "chance_near_a_miss_or_slow_wakeup": round(
                _covered([t for t, _, _ in misses] + slow, near_s, windows, t_from, t_to), 4)}


def _miss_causes(events: list[dict[str, Any]], windows: list[tuple[float, float]], t_from: float, t_to: float,
                 sentinel: dict[str, Any], near_s: float = 0.05) -> dict[str, Any]:
    """The daemon's own account of its misses outside the fault windows (:mod:`runtime.cycle_forensics`, the
    ``causes`` of its ``deadline_miss`` events): deadlines missed per cause, and per cause how many came within
    ``near_s`` of a bare loop's miss or slow wake-up (a sign of the host)."""
    host = [t for t, _, _ in sentinel.get("misses", [])] + [t for t, _ in sentinel.get("slow", [])]
    by_cause: dict[str, dict[str, int]] = {}
    worst: dict[str, dict[str, Any]] = {}
    kept: list[dict[str, Any]] = []
    for e in events:
        if e.get("event") != "deadline_miss":
            continue
        for rec in e.get("causes") or []:
            t = float(rec["t"])
            if not t_from <= t <= t_to or any(a <= t <= b for a, b in windows):
                continue
            kept.append(rec)
            c = by_cause.setdefault(rec["cause"], {"missed": 0, "records": 0, "with_host_sign": 0})
            c["missed"] += int(rec["missed"])
            c["records"] += 1
            if any(t - near_s <= th <= t + near_s for th in host):
                c["with_host_sign"] += int(rec["missed"])
            if rec["late_ms"] > worst.get(rec["cause"], {}).get("late_ms", -1.0):
                worst[rec["cause"]] = rec
    return {"by_cause": by_cause, "worst_record_per_cause": worst,
            "recorded_missed": sum(c["missed"] for c in by_cause.values()), "records": kept}


def recording_rows(path: str | None, period: float) -> dict[str, int]:
    """Rows in a ``.lrec`` file and the control cycles absent from it: the period slots its time column spans less
    its rows. A cycle run early on an input (wake on input) serves its slot ahead of the deadline, so the steps
    between rows vary by up to three quarters of a period and only the whole span counts slots (within one)."""
    import json

    import numpy as np

    if not path or not Path(path).exists():
        return {"rows": 0, "absent_cycles": 0}
    with open(path, "rb") as fh:
        header = json.loads(fh.readline())
        body = fh.read()
    rows = np.frombuffer(body[: len(body) // 8 * 8], "<f8")  # a record cut short at the end is left out
    cols = int(header["columns"])
    t = rows[: len(rows) // cols * cols].reshape(-1, cols)[:, 0]
    slots = int(np.rint((t[-1] - t[0]) / period)) + 1 if len(t) else 0
    return {"rows": len(t), "absent_cycles": max(0, slots - len(t))}


def summarize(raw: dict[str, Any], settings: dict[str, Any], settle_s: float) -> dict[str, Any]:
    """The report: settings, figures and whether each goal is met."""
    states = raw["collector"].states
    windows = _fault_windows(raw, settle_s, float(settings["interval"]))
    t_warm = raw["t0"] + float(settings["warmup_s"])
    t_end = states[-1][0] if states else t_warm
    missed = _missed(states, windows, t_warm, t_end)
    causes = _miss_causes(raw["collector"].events, windows, t_warm, t_end, raw.get("sentinel") or {})
    # the loop's own miss times, when it accounted for every miss outside fault handling (16 records a second at most)
    exact = ([(float(r["t"]), int(r["missed"])) for r in causes["records"]]
             if causes["recorded_missed"] == missed["outside_fault_handling"] else None)
    stalls = _machine_stalls(states, windows, t_warm, t_end, raw.get("sentinel") or {}, records=exact)
    runs = [r.summary() for r in raw["runs"]]
    injected = [r for r in runs if r["fault"] != "unexpected"]
    unexpected = [r for r in runs if r["fault"] == "unexpected"]
    rec = raw["record_stop"]
    period = 1.0 / float(settings["rate"])
    file_rows = recording_rows(rec.get("path"), period)
    # every cycle that ran while recording is a row: the cycles absent from the file must be deadlines the loop missed
    rec_events = [e for e in raw["collector"].events if e.get("event") == "record"]
    t_rec0 = next((e["t"] for e in rec_events if e.get("state") == "started"), t_warm)
    t_rec1 = next((e["t"] for e in rec_events if e.get("state") == "stopped"), t_end)
    missed_rec = _missed(states, [], t_rec0, t_rec1)["outside_fault_handling"]
    lost_recorded = max(0, file_rows["absent_cycles"] - missed_rec)
    s = raw["streamer"]
    late_outside = sum(n for t, n in s.late_at if not any(a <= t <= b for a, b in windows))
    mem0, mem1 = raw["memory_start"], raw["memory_end"]
    growth = mem1["total"] - mem0["total"]
    faults_ok = all((r["detected"] or r["detected_by"].startswith("nothing")) and r["recovered"] for r in injected)
    goals = {"missed_outside_faults": missed["outside_fault_handling"] <= GOAL_MISSED,
             "every_fault_detected_and_recovered": faults_ok,
             "frames_lost": lost_recorded <= GOAL_LOST and late_outside <= GOAL_LOST,
             "memory_growth": growth <= GOAL_GROWTH_MIB}
    osc = ((raw.get("status_end") or {}).get("inputs") or {}).get("osc") or {}
    return {
        "settings": settings,
        "missed_deadlines": missed,
        "machine_stalls": stalls,
        "miss_causes": causes,
        "faults": injected,
        "unexpected_faults": unexpected,
        "recording": {"samples_reported": int(rec.get("samples", 0)), "rows_in_file": file_rows["rows"],
                      "cycles_absent": file_rows["absent_cycles"], "deadlines_missed_while_recording": missed_rec,
                      "lost": lost_recorded, "dropped_by_writer": rec.get("dropped"), "path": rec.get("path")},
        "stream": {"sent": s.sent, "sent_while_active": s.sent_active, "accepted": s.accepted,
                   "accepted_of_sent_while_active": s.accepted_active, "late": s.late,
                   "late_outside_fault_handling": late_outside, "late_on_arrival": s.late_on_arrival,
                   "refused": s.refused},
        "osc": {"sent": raw["osc_sent"], "daemon_input": osc},
        "memory_mib": {"start": mem0, "end": mem1, "growth_total": round(growth, 2)},
        "loop_end": (raw.get("status_end") or {}).get("loop"),
        "daemon_exit": raw["daemon_rc"],
        "goals": goals,
        "goals_met": all(goals.values()),
    }


def print_summary(result: dict[str, Any], path: Path) -> None:
    """The figures against the goals, one line each."""
    m, r, st, mem = result["missed_deadlines"], result["recording"], result["stream"], result["memory_mib"]
    loop = result.get("loop_end") or {}
    steal = result["settings"].get("hypervisor_steal_s")
    print(f"missed deadlines outside fault handling: {m['outside_fault_handling']} (goal {GOAL_MISSED}); during "
          f"fault handling {m['during_fault_handling']}; loop total {loop.get('missed')} of {loop.get('cycles')}; "
          f"CPU time the hypervisor took from this machine meanwhile: "
          f"{'?' if steal is None else f'{steal * 1e3:.0f} ms'}")
    ms = result.get("machine_stalls") or {}
    if ms:
        print(f"  bare realtime loops beside it ({ms['scheduling']}) missed {ms['missed_outside_fault_handling']} "
              f"outside fault handling (worst {ms['worst_lateness_ms']} ms late): {ms['daemon_misses_with_one']} of "
              f"the daemon's {ms['daemon_misses_outside']} came within 50 ms of one of those")
        if "slow_wakeups_outside_fault_handling" in ms:
            print(f"  their probe (fixed interpreter work, median {ms['probe_median_us']} µs) ran over "
                  f"{ms['slow_factor']}x its median at {ms['slow_wakeups_outside_fault_handling']} wake-ups outside "
                  "fault handling: "
                  f"{ms['daemon_misses_with_a_miss_or_slow_wakeup']} of the daemon's "
                  f"{ms['daemon_misses_outside']} came within 50 ms of a miss or a slow wake-up (matched by "
                  f"{ms.get('matched_by', '?')}; a moment picked at random comes that near with chance "
                  f"{ms.get('chance_near_a_miss_or_slow_wakeup', float('nan')):.3f})")
    mc = result.get("miss_causes") or {}
    if mc.get("by_cause"):
        parts = ", ".join(f"{k} {v['missed']} ({v['with_host_sign']} near a sign of the host)"
                          for k, v in sorted(mc["by_cause"].items(), key=lambda kv: -kv[1]["missed"]))
        print(f"  the loop's own account of {mc['recorded_missed']} of them (runtime.cycle_forensics): {parts}")
    for f in result["faults"] + result["unexpected_faults"]:
        ttf = "-" if f["time_to_fault_s"] is None else f"{f['time_to_fault_s']:.2f} s"
        ttr = "-" if f["time_to_recover_s"] is None else f"{f['time_to_recover_s']:.2f} s"
        print(f"  {f['fault']:<18} detected {f['detected']!s:<5} time to fault {ttf:>7}  recovered "
              f"{f['recovered']!s:<5} time to recover {ttr:>7}  {f['detected_by'][:90]}")
        if f["fault"] == "unexpected":
            print(f"    (not injected: {f['what'][:110]})")
    print(f"recording: {r['rows_in_file']} rows ({r['samples_reported']} reported), {r['cycles_absent']} cycles absent "
          f"for {r['deadlines_missed_while_recording']} missed deadlines: lost {r['lost']} (goal {GOAL_LOST}); "
          f"stream: {st['accepted']} of {st['sent']} frames accepted, {st['late']} late "
          f"({st['late_outside_fault_handling']} outside fault handling, goal {GOAL_LOST}; "
          f"{st['late_on_arrival']} already older than the 50 ms buffer when the daemon received them), "
          f"refused {st['refused']}")
    print(f"daemon processes VmRSS: {mem['start']['total']:.1f} MiB after warm-up, {mem['end']['total']:.1f} MiB at "
          f"the end: growth {mem['growth_total']:+.2f} MiB (goal <= {GOAL_GROWTH_MIB:g})")
    print(f"goals: {result['goals']} -> {'met' if result['goals_met'] else 'NOT met'}; report {path}")


def write_timeline(raw: dict[str, Any], result: dict[str, Any], path: Path) -> None:
    """Jaw commanded/measured, cumulative missed deadlines, feedback age and the daemon's memory over time, with
    each fault's handling shaded and named."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = raw["t0"]
    states = raw["collector"].states
    t = [s[0] - t0 for s in states]
    fig, axes = plt.subplots(4, 1, figsize=(12, 9), sharex=True)
    axes[0].plot(t, [s[4] for s in states], lw=0.8, label="jaw commanded")
    axes[0].plot(t, [s[5] for s in states], lw=0.8, label="jaw measured")
    axes[0].set_ylabel("jaw (deg)")
    axes[0].legend(loc="upper right", fontsize=8)
    missed0 = states[0][2] if states else 0
    axes[1].step(t, [s[2] - missed0 for s in states], where="post", color="C3", label="daemon (state messages)")
    bare = sorted((m[0] - t0, m[1]) for m in (raw.get("sentinel") or {}).get("misses", []) if m[0] >= t0)
    if bare:  # the bare realtime loops beside it: their misses are the host's
        cum = [0]
        for _, n in bare:
            cum.append(cum[-1] + n)
        t_last = max(t[-1] if t else 0.0, bare[-1][0])
        axes[1].step([0.0, *(b[0] for b in bare), t_last], [*cum, cum[-1]], where="post", color="0.5", lw=0.8,
                     label="bare realtime loops beside it (the host)")
    own = [float(r["t"]) - t0 for r in (result.get("miss_causes") or {}).get("records", [])]
    if own:
        axes[1].plot(own, [0.0] * len(own), "|", color="C3", ms=12,
                     label="daemon's misses outside fault handling, at their own times")
    axes[1].legend(loc="upper left", fontsize=7)
    axes[1].set_ylabel("missed deadlines\n(cumulative)")
    axes[2].plot(t, [1e3 * s[6] if not math.isnan(s[6]) else math.nan for s in states], lw=0.6, color="C2")
    axes[2].set_ylabel("oldest bus\nfeedback (ms)")
    axes[2].set_yscale("log")
    axes[3].plot([m[0] - t0 for m in raw["memory"]], [m[1] for m in raw["memory"]], marker=".", color="C4")
    axes[3].set_ylabel("daemon VmRSS (MiB)")
    axes[3].set_xlabel("time (s)")
    for run in raw["runs"]:
        end = (run.t_recovered or run.t_inject + 5.0) - t0
        color = "red" if run.name == "unexpected" or run.t_recovered is None else "C1"
        for ax in axes:
            ax.axvspan(run.t_inject - t0, end, color=color, alpha=0.15)
        axes[0].annotate(run.name.replace("_", " "), (run.t_inject - t0, 1.0), xycoords=("data", "axes fraction"),
                         fontsize=7, rotation=90, va="top")
        if run.t_detected is not None:
            axes[1].axvline(run.t_detected - t0, color="k", lw=0.6, ls=":")
    s = result["settings"]
    fig.suptitle(f"soak: sample head at {s['rate']:g} Hz, {s['minutes']:g} min, a fault every {s['interval']:g} s "
                 f"(shaded: from injection to the head active again; red: not injected, or not recovered)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
