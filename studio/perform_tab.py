"""Perform tab: send the clip and play it through the daemon; enable, disable, reset; a live telemetry mirror.

Everything goes through the protocol (``load_clip``, ``play``, ``stop``, ``enable``, ``disable``, ``reset``), so the
daemon's own validation and safety path apply. The mirror redraws a few times a second: commanded against measured
traces of a chosen channel, lifecycle and mode, loop rate and missed deadlines, bus states, faults, the guard, and
the latest events.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import viser

from models.client import DaemonError, DaemonTimeout
from studio.clipdoc import ClipError

if TYPE_CHECKING:
    from studio.app import Studio

#: Mirror redraws per second.
MIRROR_HZ = 4.0


def _event_text(e: dict[str, Any]) -> str:
    kind = e.get("event", "?")
    rest = ", ".join(f"{k}={v}" for k, v in e.items() if k not in ("event", "t") and not isinstance(v, dict))
    return f"`{e.get('t', 0.0):.2f}` **{kind}** {rest}"


class PerformTab:
    """The Perform tab's controls and its mirror thread."""

    def __init__(self, studio: Studio) -> None:
        self.studio = studio
        gui = studio.server.gui
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if studio.daemon is None:
            gui.add_markdown("No daemon connected. Start the studio with `--daemon tcp://HOST:PORT` (the daemon's "
                             "command endpoint) to send clips, play them on the head and mirror its telemetry.")
            return
        self.state_text = gui.add_markdown("Waiting for telemetry…")
        with gui.add_folder("Lifecycle"):
            self.enable_button = gui.add_button("Enable", icon=viser.Icon.POWER, color="green")
            self.enable_button.on_click(lambda _: self._request("enable"))
            self.disable_button = gui.add_button("Disable", icon=viser.Icon.POWER)
            self.disable_button.on_click(lambda _: self._request("disable"))
            self.reset_button = gui.add_button("Reset", icon=viser.Icon.REFRESH,
                                               hint="Clear a latched e-stop or a fault (the head is then inactive)")
            self.reset_button.on_click(lambda _: self._request("reset"))
        with gui.add_folder("Clip"):
            self.loop = gui.add_checkbox("Loop on head", initial_value=False)
            self.speed = gui.add_slider("Speed", min=0.1, max=2.0, step=0.05, initial_value=1.0)
            self.play_button = gui.add_button("Send and play", icon=viser.Icon.PLAYER_PLAY,
                                              hint="load_clip the Animate tab's clip, then play it")
            self.play_button.on_click(lambda _: self.send_and_play())
            self.stop_button = gui.add_button("Stop on head", icon=viser.Icon.PLAYER_STOP)
            self.stop_button.on_click(lambda _: self._request("stop"))
            self.reply_text = gui.add_markdown("")
        actuators = studio.head.names
        self.trace_channel = gui.add_dropdown("Trace channel", options=actuators, initial_value=actuators[0])
        self.trace = gui.add_uplot(
            data=(np.array([0.0, 1.0]), np.zeros(2), np.zeros(2)),
            series=({"label": "t (s)"}, {"label": "commanded", "stroke": "#1f77b4", "width": 2},
                    {"label": "measured", "stroke": "#ff7f0e", "width": 2}),
            title="Commanded vs measured", aspect=1.6, scales={"x": {"time": False}})
        self.buses_text = gui.add_markdown("")
        self.events_text = gui.add_markdown("")
        self._thread = threading.Thread(target=self._run, name="studio-mirror", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ commands
    def _request(self, op: str, **fields: Any) -> dict[str, Any] | None:
        daemon = self.studio.daemon
        assert daemon is not None
        try:
            reply = daemon.call(op, **fields)
        except (DaemonError, DaemonTimeout) as exc:
            self.reply_text.content = f"**{op} refused**: {exc}"
            return None
        self.reply_text.content = f"`{op}`: ok" + (f", lifecycle {reply['lifecycle']}" if "lifecycle" in reply else "")
        return reply

    def send_and_play(self) -> None:
        doc = self.studio.doc
        try:
            clip = doc.to_dict()
        except ClipError as exc:
            self.reply_text.content = f"**Nothing to send**: {exc}"
            return
        loaded = self._request("load_clip", clip=clip)
        if loaded is None:
            return
        played = self._request("play", clip=loaded["clip"], loop=bool(self.loop.value), speed=float(self.speed.value))
        if played is not None:
            self.reply_text.content = (f"Playing `{loaded['clip']}` ({loaded['duration']:.2f} s, {loaded['keys']} "
                                       f"keys) from daemon time {played['start']:.3f}.")

    # ------------------------------------------------------------------ mirror
    def _run(self) -> None:
        while not self._stop.wait(1.0 / MIRROR_HZ):
            if time.monotonic() < self.studio.posing_until:  # a slider is moving: its skin frames go first
                continue
            try:
                self.redraw()
            except Exception as exc:  # keep the mirror alive; say what went wrong on the page
                self.state_text.content = f"**Mirror error**: {exc}"

    def redraw(self) -> None:
        daemon = self.studio.daemon
        assert daemon is not None
        m = daemon.snapshot()
        loop = m.loop
        st = m.status
        fault = st.get("fault")
        estop = st.get("estop")
        clip = m.clip or (st.get("timeline") or {})
        lines = [
            f"**Lifecycle** `{m.lifecycle}`" + (f" (e-stop: {estop})" if estop else "") + f" · mode `{m.mode}`",
            f"**Loop** {loop.get('rate_hz', 0):.0f} Hz, {loop.get('cycles', 0)} cycles, "
            f"**missed deadlines** {loop.get('missed', 0)}, jitter p99 {loop.get('jitter_p99_us', 0):.0f} µs",
            f"**Clip** `{clip.get('name') or clip.get('clip') or '-'}` "
            f"{min(clip.get('time', 0) or 0, clip.get('duration', 0) or 0):.2f} / {clip.get('duration', 0) or 0:.2f} s",
            f"**Fault** {fault}" if fault else "**Fault** none",
            f"**Guard** {(st.get('guard') or {}).get('verdict', '-')}",
        ]
        if not m.connected:
            lines.insert(0, "**Daemon not answering**")
        self.state_text.content = "  \n".join(lines)
        buses = st.get("buses") or {}
        ages = st.get("feedback_age_s") or {}
        self.buses_text.content = "**Buses** " + (", ".join(
            f"`{b}` {s}" + (f" ({ages[b] * 1e3:.0f} ms)" if isinstance(ages.get(b), int | float) else "")
            for b, s in buses.items()) or "-")
        self.events_text.content = "**Events**  \n" + ("  \n".join(_event_text(e) for e in list(m.events)[-6:][::-1])
                                                       or "none yet")
        ch = str(self.trace_channel.value)
        if len(m.times) >= 2:
            t = np.asarray(m.times, dtype=np.float64)
            cmd = np.array([c.get(ch, np.nan) if c.get(ch) is not None else np.nan for c in m.commanded])
            meas = np.array([x.get(ch) if x.get(ch) is not None else np.nan for x in m.measured], dtype=np.float64)
            self.trace.data = (t - t[-1], cmd, meas)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
