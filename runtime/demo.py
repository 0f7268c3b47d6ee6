"""The demo's performance on a running daemon (what ``likeness demo`` runs): enable the head, play and record each
clip with a progress bar, stop at the first fault or e-stop, and collect the recordings and the loop's status."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from models.client import Client, Telemetry
from models.clip import Clip


@dataclass
class FeedbackSeen:
    """What one performance showed of the buses' feedback: the largest feedback age per bus (from the state
    messages and the ``feedback_late`` events) and how often each bus was reported late."""

    max_age: dict[str, float] = field(default_factory=dict)
    late: dict[str, int] = field(default_factory=dict)
    limit: dict[str, float] = field(default_factory=dict)

    def take(self, topic: str, body: Mapping[str, Any]) -> None:
        """Fold one telemetry message in."""
        ages: Mapping[str, Any] = {}
        if topic == "state":
            ages = body.get("feedback_age_s") or {}
        elif topic == "event" and body.get("event") == "feedback_late":
            bus = str(body["bus"])
            ages = {bus: body.get("age")}
            self.limit[bus] = float(body.get("limit", 0.0))
            if body.get("state") == "late":
                self.late[bus] = self.late.get(bus, 0) + 1
        for bus, age in ages.items():
            if isinstance(age, int | float) and age == age and age != float("inf"):
                self.max_age[bus] = max(self.max_age.get(bus, 0.0), float(age))


@dataclass
class MissesSeen:
    """The loop's missed deadlines during one performance, by the cause its own record names (the ``causes`` of its
    ``deadline_miss`` events, :mod:`runtime.cycle_forensics`)."""

    by_cause: dict[str, int] = field(default_factory=dict)

    def take(self, topic: str, body: Mapping[str, Any]) -> None:
        """Fold one telemetry message in."""
        if topic != "event" or body.get("event") != "deadline_miss":
            return
        for rec in body.get("causes") or []:
            cause = str(rec.get("cause", "unknown"))
            self.by_cause[cause] = self.by_cause.get(cause, 0) + int(rec.get("missed", 1))


@dataclass
class DemoRun:
    """What the performance left: each played clip with its recording's ``record stop`` reply and what its buses'
    feedback showed, the daemon's last status, and the fault or e-stop event that cut it short (None when every
    clip played)."""

    recordings: list[tuple[Clip, dict[str, Any]]] = field(default_factory=list)
    feedback: dict[str, FeedbackSeen] = field(default_factory=dict)
    misses: dict[str, MissesSeen] = field(default_factory=dict)
    status: dict[str, Any] = field(default_factory=dict)
    fault: dict[str, Any] | None = None


def demo_overrides(out: Path, rate: float | None = None, realtime: bool = True) -> dict[str, object]:
    """Daemon settings for the demo: any free loopback ports, recordings into ``out``, the rate and priority."""
    overrides: dict[str, object] = {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                                    "runtime.record_dir": str(out)}
    if rate:
        overrides["runtime.rate_hz"] = rate
    if not realtime:
        overrides["runtime.realtime"] = False
    return overrides


def play_performance(command_endpoint: str, telemetry_endpoint: str,
                     clips: Sequence[tuple[Mapping[str, Any], Clip]],
                     say: Callable[..., None] = print) -> DemoRun:
    """Enable the head, then load, record and play each clip in order (``say`` prints the progress); disable the
    head at the end unless a fault or e-stop stopped the performance."""
    import time

    result = DemoRun()
    with Client(command_endpoint, timeout=10.0) as client, Telemetry(telemetry_endpoint) as tel:
        client.call("enable")
        time.sleep(0.2)  # let the telemetry subscription settle
        for data, clip in clips:
            seen = result.feedback[clip.name] = FeedbackSeen()
            misses = result.misses[clip.name] = MissesSeen()
            result.fault = _play(client, tel, data, clip, say, seen, misses)
            rec_reply = client.call("record", action="stop")
            if result.fault is not None:
                break
            result.recordings.append((clip, rec_reply))
        result.status = client.call("status")
        if result.fault is None:
            client.call("disable")
    return result


def _play(client: Client, tel: Telemetry, data: Mapping[str, Any], clip: Clip,
          say: Callable[..., None], seen: FeedbackSeen, misses: MissesSeen) -> dict[str, Any] | None:
    """Load, record and play one clip with a progress bar, watching the buses' feedback age (``seen``) and the
    loop's missed deadlines (``misses``); returns the fault or e-stop event that cut it short."""
    reply = client.call("load_clip", clip=data)
    say(f"performance {clip.name!r}: {reply['duration']:.2f} s, {len(reply['channels'])} channels, "
        f"{reply['keys']} keys")
    client.call("record", action="start", name=clip.name)
    start = client.call("play", clip=clip.name)["start"]
    duration = reply["duration"]
    shown = -1
    while True:
        stop = None
        msg = tel.recv(0.5)
        while msg is not None:  # every message that came meanwhile, so no late event goes unseen
            seen.take(msg[0], msg[1])
            misses.take(msg[0], msg[1])
            if msg[0] == "event" and msg[1]["event"] in ("fault", "estop") and stop is None:
                stop = msg[1]
            msg = tel.recv(0.0)
        now = client.call("clock")["t_send"]
        if stop is not None:
            say()
            return stop
        pct = int(min(1.0, max(0.0, (now - start) / duration)) * 100)
        if pct // 5 != shown:
            shown = pct // 5
            bar = "#" * (pct // 5) + "." * (20 - pct // 5)
            say(f"\r  playing [{bar}] {pct:3d}%  {now - start:5.2f}/{duration:.2f} s", end="", flush=True)
        if now - start > duration + 0.5:
            say()
            return None
