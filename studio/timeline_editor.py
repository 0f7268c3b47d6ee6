"""The server side of the page's timeline editor: its requests (select, drag keys and handles, delete, undo, redo,
scrub, play with audio, on the head too) applied to the clip, and the timeline's state published back.

The page (``static/timeline.js``) talks over the studio's own socket (:class:`studio.skinsocket.SkinSocket`):
requests are JSON maps with an ``op``; the state goes out as the ``timeline`` topic after every change and the
playhead as the ``playhead`` topic. While the page plays, its audio clock is the master: the page sends the clip
time it hears (``tick``) and the skin follows it, so preview and sound cannot drift apart. Played on the head, the
clip starts on the daemon at a scheduled daemon-clock time (``play`` ``at``, the offset estimated with ``clock``)
and the page starts the sound the same delay after the reply.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from studio.clipdoc import ClipError
from studio.timeline import Audio, timeline_state

if TYPE_CHECKING:
    from studio.animate_tab import AnimateTab

#: Time from the play request to the scheduled start on the head and in the page (s): the clip's upload and the
#: reply to the page fit in it.
PLAY_LEAD_S = 0.3
#: Clock samples taken to estimate the daemon's clock offset (the one with the smallest round trip is kept).
CLOCK_SAMPLES = 5


class TimelineEditor:
    """Applies the page timeline's requests to the Animate tab's clip and publishes the timeline."""

    def __init__(self, tab: AnimateTab) -> None:
        self.tab = tab
        self.studio = tab.studio
        self.audio: Audio | None = None
        self.head_playing = False
        self.studio.socket.on_request(self.handle)

    # ------------------------------------------------------------------ out
    def publish(self) -> None:
        """Send the timeline's state (tracks, keys, curves, selection, audio, undo) to the pages."""
        tab = self.tab
        head = self.studio.head
        state = timeline_state(self.studio.doc, {c.name: (c.min, c.max) for c in head.channels},
                               tuple(c.name for c in head.channels), float(tab.length.value),
                               float(tab.time.value), tab._selected, self.audio)
        state["head"] = self.studio.daemon is not None
        self.studio.socket.publish("timeline", state)

    def publish_playhead(self, t: float) -> None:
        self.studio.socket.publish("playhead", {"t": float(t)})

    # ------------------------------------------------------------------ in
    def handle(self, request: dict[str, Any], reply: Callable[[dict[str, Any]], None]) -> None:
        """One request from a page; an edit the clip refuses is answered with ``{"type": "refused", ...}``."""
        op = request.get("op")
        handler = self._ops().get(str(op))
        if handler is None:
            reply({"type": "error", "error": f"unknown timeline request {op!r}"})
            return
        try:
            with self.studio.pose_lock:
                answer = handler(request)
        except (ClipError, KeyError, TypeError, ValueError) as exc:
            reply({"type": "refused", "op": op, "error": str(exc)})
            self.publish()  # the page drops its unconfirmed edit
            return
        if answer is not None:
            reply(answer)

    def _ops(self) -> dict[str, Callable[[dict[str, Any]], dict[str, Any] | None]]:
        return {"select": self._select, "move_key": self._move_key, "set_handles": self._set_handles,
                "delete_key": self._delete_key, "undo": self._undo, "redo": self._redo, "scrub": self._scrub,
                "tick": self._tick, "audio": self._audio, "play": self._play, "stop": self._stop,
                "refresh": lambda _: self.publish()}

    def _key_ref(self, r: dict[str, Any]) -> tuple[str, int]:
        ch, i = str(r["channel"]), int(r["index"])
        if ch not in self.studio.doc.tracks or not 0 <= i < len(self.studio.doc.tracks[ch].keys):
            raise ClipError(f"channel {ch!r} has no key #{i + 1}")
        return ch, i

    def _select(self, r: dict[str, Any]) -> None:
        ch, i = self._key_ref(r)
        self.tab.channel.value = ch
        self.tab.select_key(ch, i)

    def _move_key(self, r: dict[str, Any]) -> None:
        ch, i = self._key_ref(r)
        t, v = _finite(r["t"], "t"), _finite(r["value"], "value")
        j = self.studio.doc.move_key(ch, i, round(max(t, 0.0), 6), v)
        self.tab._selected = (ch, j)
        self.tab.channel.value = ch
        self.tab.redraw()

    def _set_handles(self, r: dict[str, Any]) -> None:
        ch, i = self._key_ref(r)
        h = [_finite(x, "handle") for x in r["handles"]]
        if len(h) != 4:
            raise ClipError(f"handles need four numbers (in_dt, in_dv, out_dt, out_dv), got {len(h)}")
        self.studio.doc.set_handles(ch, i, (h[0], h[1], h[2], h[3]))
        self.tab._selected = (ch, i)
        self.tab.channel.value = ch
        self.tab.redraw()

    def _delete_key(self, r: dict[str, Any]) -> None:
        ch, i = self._key_ref(r)
        self.studio.doc.remove_key(ch, self.studio.doc.tracks[ch].keys[i].t)
        self.tab._selected = None
        self.tab.redraw()

    def _undo(self, _: dict[str, Any]) -> None:
        self.studio.doc.undo()
        self.tab.redraw()

    def _redo(self, _: dict[str, Any]) -> None:
        self.studio.doc.redo()
        self.tab.redraw()

    def _scrub(self, r: dict[str, Any]) -> None:
        t = min(max(_finite(r["t"], "t"), 0.0), float(self.tab.time.max))
        self.tab.time.value = round(t, 3)
        self.tab.show_time(t)

    def _tick(self, r: dict[str, Any]) -> None:
        """The page's audio clock while it plays: pose the skin at that clip time."""
        t = max(_finite(r["t"], "t"), 0.0)
        if t > float(self.tab.time.max):
            self.tab.time.max = round(t, 3)
        self.tab.time.value = round(t, 3)
        self.tab.show_time(t, playhead=False)

    def _audio(self, r: dict[str, Any]) -> None:
        name, duration = str(r.get("name") or "audio"), _finite(r["duration"], "duration")
        if duration <= 0:
            raise ValueError(f"audio duration must be > 0 s, got {duration}")
        self.audio = Audio(name[:200], duration)
        if duration > float(self.tab.time.max):
            self.tab.time.max = round(duration, 3)
        self.tab.redraw()

    def _play(self, r: dict[str, Any]) -> dict[str, Any]:
        """Start playing from clip time ``t``; with ``head``, on the daemon at a scheduled time too. The reply's
        ``after_request_s`` is when, after sending the request, the page starts its sound (``delay_s``: after the
        reply)."""
        received = time.monotonic()
        t0 = max(_finite(r.get("t", 0.0), "t"), 0.0)
        if not r.get("head"):
            return {"type": "play", "t": t0, "delay_s": 0.0, "head": False}
        daemon = self.studio.daemon
        if daemon is None:
            raise ValueError("no daemon connected: start the studio with --daemon to play on the head")
        daemon.send_clip(self.studio.doc.to_dict())
        offset = self._daemon_offset()
        start = time.monotonic() + PLAY_LEAD_S
        answer = daemon.call("play", clip=self.studio.doc.name, at=start + offset, **{"from": t0})
        self.head_playing = True
        # The page times its start from when it sent the request (its reply may wait behind the page's drawing).
        return {"type": "play", "t": t0, "delay_s": max(start - time.monotonic(), 0.0), "head": True,
                "after_request_s": start - received, "at": float(answer.get("start", start + offset))}

    def _daemon_offset(self) -> float:
        """Daemon clock minus this host's monotonic clock, from the ``clock`` sample with the smallest round trip."""
        daemon = self.studio.daemon
        assert daemon is not None
        best: tuple[float, float] | None = None
        for _ in range(CLOCK_SAMPLES):
            t0 = time.monotonic()
            r = daemon.call("clock")
            t1 = time.monotonic()
            trip = (t1 - t0) - (float(r["t_send"]) - float(r["t_recv"]))
            offset = ((float(r["t_recv"]) - t0) + (float(r["t_send"]) - t1)) / 2.0
            if best is None or trip < best[0]:
                best = (trip, offset)
        assert best is not None
        return best[1]

    def _stop(self, r: dict[str, Any]) -> None:
        if self.head_playing and self.studio.daemon is not None:
            self.head_playing = False
            self.studio.daemon.call("stop")
        self.publish()


def _finite(x: Any, what: str) -> float:
    v = float(x)
    if not math.isfinite(v):
        raise ValueError(f"{what} must be a finite number, got {x!r}")
    return v
