"""Pose tab: a slider per actuator, group and ARKit target channel; the guard's verdict; the exact FEM pose.

Each slider is named after its channel (its accessible name too) and moves in the channel's configured unit within
its limits. Moving an actuator or group slider sets those actuators; moving a target slider solves every target
slider's weights to actuator values through the predictor. The other sliders follow the resulting pose.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import viser

from studio.skin import ERROR_COLORS, ERROR_EDGES_MM, STRAIN_COLORS, UNMEASURED, SkinFrame

if TYPE_CHECKING:
    from studio.app import Studio


#: Seconds after a slider value from the page during which the studio's other page updates wait (a drag sends a
#: value every few tens of milliseconds).
POSING_S = 0.4


def _step(lo: float, hi: float, unit: str) -> float:
    if unit == "weight":
        return 0.01
    return 0.1 if hi - lo <= 200 else 1.0


def _swatch(rgb: tuple[int, int, int], text: str) -> str:
    return f'<span style="display:inline-block;width:0.9em;height:0.9em;background:rgb{rgb};' \
           f'margin-right:0.3em;vertical-align:middle"></span>{text}'


class PoseTab:
    """The Pose tab's controls (built inside the tab's context)."""

    def __init__(self, studio: Studio) -> None:
        from studio.fem_worker import ExactPoser

        self.studio = studio
        head = studio.head
        gui = studio.server.gui
        self.verdict = gui.add_markdown("…")
        lo, hi = head.guard.strain_range
        labels = ("< 50 %", "50–70 %", "70–85 %", "85–100 %", "beyond: refused")
        legend = " ".join(_swatch(c, t) for c, t in zip(STRAIN_COLORS, labels, strict=True))
        legend += " " + _swatch(UNMEASURED, "not measured (beside attachments)")
        self.legend = gui.add_html(f'<div style="font-size:0.8em;padding:0 0.6em">Strain as a share of the validated '
                                   f'range ({lo * 100:+.0f} % … {hi * 100:+.0f} %): {legend}</div>')
        self.neutral_button = gui.add_button("Neutral pose", icon=viser.Icon.REFRESH)
        self.neutral_button.on_click(lambda _: self.studio.set_pose(head.neutral.copy()))
        self.sliders: dict[str, Any] = {}
        for kind, title, open_ in (("actuator", "Actuators", True), ("group", "Groups", True),
                                   ("target", "ARKit targets", False)):
            chans = [c for c in head.channels if c.kind == kind]
            if not chans:
                continue
            with gui.add_folder(title, expand_by_default=open_):
                for c in chans:
                    s = gui.add_slider(c.name, min=round(c.min, 4), max=round(c.max, 4),
                                       step=_step(c.min, c.max, c.unit), initial_value=round(c.neutral, 4),
                                       hint=f"{c.name} ({c.unit}, {c.min:.4g} … {c.max:.4g})")
                    s.on_update(self._on_slider(c.name, kind))
                    self.sliders[c.name] = s
        # The page reads a pose slider's new value from the key or pointer event itself (as the slider computes it)
        # and sends it on the studio's socket at once: it needs each slider's range and step.
        studio.socket.publish("sliders", {"sliders": {n: [s.min, s.max, s.step] for n, s in self.sliders.items()}})
        with gui.add_folder("Exact FEM pose"):
            self.exact_button = gui.add_button("Run exact FEM pose", icon=viser.Icon.PLAYER_PLAY,
                                               hint="Solve this pose with the skin FEM in a worker process and show "
                                                    "the predictor's error against it (0–4 mm)")
            self.exact_button.on_click(lambda _: self.run_exact())
            self.exact_text = gui.add_markdown("The FEM runs in a worker process; the first solve also compiles "
                                               "its kernels (about a minute), later ones take seconds.")
            self.exact_legend = gui.add_html("", visible=False)
            self.strain_button = gui.add_button("Show strain map", visible=False)
            self.strain_button.on_click(lambda _: self.studio.set_pose(self.studio.p))
        self._poser = ExactPoser(head.spec.source)
        self._exact_lock = threading.Lock()
        #: Per slider, the values the page sent on the studio's socket that viser's own update has not yet repeated.
        self._fast: dict[str, deque[float]] = {}
        studio.socket.on_request(self._on_fast_slider, ops=("slider",))

    # ------------------------------------------------------------------ sliders
    def _on_slider(self, name: str, kind: str) -> Any:
        def handler(event: viser.GuiEvent) -> None:
            if event.client_id is None:  # set by the studio itself (following a pose)
                return
            value = float(event.target.value)
            self.studio.posing_until = time.monotonic() + POSING_S
            with self.studio.pose_lock:
                if self._already_fast(name, value):
                    return
                self._move(name, kind, value, source=event.target)
        return handler

    def _move(self, name: str, kind: str, value: float, source: object, fast: bool = False) -> bool:
        """Set the pose a slider's new value gives (caller holds the pose lock); False when it changes nothing: a
        pose already there, or (``fast``, from the page's socket) a target weight viser's update already brought."""
        head = self.studio.head
        if kind == "target":
            weights = {n: float(s.value) for n, s in self.sliders.items() if head.by_name[n].kind == "target"}
            if fast and weights[name] == value:
                return False
            weights[name] = value
            p, _ = head.solve_targets(weights, self.studio.p)
        else:
            p = head.apply(self.studio.p, {name: value})
            if np.array_equal(p, self.studio.p):
                return False
        self.studio.set_pose(p, source=source)
        return True

    def _on_fast_slider(self, request: dict[str, Any], reply: Callable[[dict[str, Any]], None]) -> None:
        """A slider value from the page's own socket (``{"op": "slider", "name", "value"}``), ahead of viser's copy
        of the same move. Names that are not pose channels (other tabs' sliders) are ignored."""
        name, value = request.get("name"), request.get("value")
        slider = self.sliders.get(str(name))
        if slider is None or not isinstance(value, int | float) or not np.isfinite(value):
            return
        c = self.studio.head.by_name[str(name)]
        value = float(np.clip(value, c.min, c.max))
        self.studio.posing_until = time.monotonic() + POSING_S
        with self.studio.pose_lock:
            if self._move(c.name, c.kind, value, source=slider, fast=True):
                self._fast.setdefault(c.name, deque(maxlen=64)).append(value)

    def _already_fast(self, name: str, value: float) -> bool:
        """True when viser's update repeats a value the page's socket already brought (then it and every older
        pending value are dropped: a late copy must not take the slider back)."""
        pending = self._fast.get(name)
        if not pending:
            return False
        for i, v in enumerate(pending):
            if abs(v - value) <= 1e-9 * max(1.0, abs(v)):
                for _ in range(i + 1):
                    pending.popleft()
                return True
        return False

    def follow(self, p: np.ndarray, source: object = None) -> None:
        """Move the actuator and group sliders to pose ``p`` (SI) without re-triggering a pose."""
        head = self.studio.head
        values = head.channel_values(p)
        for g in head.spec.groups:
            if g.name in self.sliders:
                first = g.actuators[0]
                gain = g.gains[0] or 1.0
                values[g.name] = values[first] / gain
        for name, v in values.items():
            s = self.sliders.get(name)
            if s is None or s is source:
                continue
            c = head.by_name[name]
            s.value = round(float(np.clip(v, c.min, c.max)), 4)

    def show_verdict(self, frame: SkinFrame) -> None:
        self.verdict.content = f"**Guard**: {frame.verdict}"
        if self.strain_button.visible:
            self.strain_button.visible = False
            self.exact_legend.visible = False

    # ------------------------------------------------------------------ exact FEM pose
    def run_exact(self) -> None:
        if not self._exact_lock.acquire(blocking=False):
            self.exact_text.content = "An exact solve is already running."
            return
        p = self.studio.p.copy()
        self.exact_button.disabled = True
        self.exact_text.content = "Solving the exact FEM pose in a worker process…"
        t0 = time.monotonic()
        future = self._poser.submit(p)

        def done(fut: Any) -> None:
            try:
                exact, converged, iterations = fut.result()
                predicted = self.studio.head.predictor.predict(p)
                worst, mean = self.studio.view.show_error(predicted, exact)
                legend = " ".join(_swatch(c, f"{lo:.0f}–{hi:.0f} mm" if hi < 99 else f">{lo:.0f} mm")
                                  for c, lo, hi in zip(ERROR_COLORS, (0.0, *ERROR_EDGES_MM),
                                                       (*ERROR_EDGES_MM, 99.0), strict=True))
                self.exact_text.content = (
                    f"**Predictor error vs exact FEM** (pose as posed {time.monotonic() - t0:.0f} s ago; "
                    f"{'converged' if converged else 'NOT converged'}, {iterations} Newton iterations): "
                    f"max {worst:.2f} mm, mean {mean:.2f} mm.")
                self.exact_legend.content = f'<div style="font-size:0.8em;padding:0 0.6em">{legend}</div>'
                self.exact_legend.visible = True
                self.strain_button.visible = True
            except Exception as exc:  # shown on the page: the worker's failure must not pass silently
                self.exact_text.content = f"**Exact FEM pose failed**: {exc}"
            finally:
                self.exact_button.disabled = False
                self._exact_lock.release()

        future.add_done_callback(done)

    def close(self) -> None:
        self._poser.close()
