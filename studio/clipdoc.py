"""An editable clip: keyframes per channel with step, linear or Bezier interpolation, in the protocol's clip schema.

The document is what the Animate tab edits and what is saved, loaded and sent to the daemon: ``to_dict`` gives the
protocol's clip map (``docs/protocol.md``, ``load_clip``), ``from_dict`` reads one (validated by
:func:`models.clip.clip_from_dict`, so a file the daemon would refuse is refused here with the same message).
Bezier keys keep tangent handles read from a file; keys made in the studio get flat handles a third of the way to
their neighbours (ease in and out), recomputed as keys move. Values are in each channel's configured unit.
Every edit can be undone and redone (:meth:`ClipDoc.undo`, :meth:`ClipDoc.redo`); edits made inside
:meth:`ClipDoc.batch` (e.g. keying every actuator at once) are one step.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from models.clip import INTERPS, Curve, clip_from_dict, make_curve

#: Two keys closer than this (s) are the same key.
TIME_EPS = 1e-6
#: Undo steps kept.
UNDO_DEPTH = 200

#: A document's content as plain immutable values (an undo step): name and per channel interpolation and keys.
State = tuple[str, tuple[tuple[str, str, tuple[tuple[float, float, tuple[float, float, float, float] | None], ...]],
                         ...]]


@dataclass
class Key:
    """One keyframe; ``handles`` = (in_dt, in_dv, out_dt, out_dv) for Bezier keys from a file, else None (auto)."""

    t: float
    value: float
    handles: tuple[float, float, float, float] | None = None


@dataclass
class Track:
    """One channel's keys (sorted by time) and interpolation."""

    interp: str = "linear"
    keys: list[Key] = field(default_factory=list)

    def rows(self) -> list[list[float]]:
        """The protocol's key rows: ``[t, v]``, or ``[t, v, in_dt, in_dv, out_dt, out_dv]`` for Bezier."""
        if self.interp != "bezier":
            return [[k.t, k.value] for k in self.keys]
        out = []
        for i, k in enumerate(self.keys):
            if k.handles is not None:
                out.append([k.t, k.value, *k.handles])
                continue
            before = (self.keys[i - 1].t - k.t) / 3.0 if i > 0 else 0.0
            after = (self.keys[i + 1].t - k.t) / 3.0 if i + 1 < len(self.keys) else 0.0
            out.append([k.t, k.value, before, 0.0, after, 0.0])
        return out


class ClipError(ValueError):
    """An edit or a file the clip schema refuses; the message names what and where."""


class ClipDoc:
    """A named clip being edited; ``version`` increases with every edit (views redraw when it changes)."""

    def __init__(self, name: str = "take") -> None:
        self.name = check_name(name)
        self.tracks: dict[str, Track] = {}
        self.version = 0
        self._curves: dict[str, Curve] | None = None
        self._saved: State = self._state()
        self._undo: list[State] = []
        self._redo: list[State] = []
        self._batch = 0

    # ------------------------------------------------------------------ history
    def _state(self) -> State:
        return (self.name, tuple((ch, tr.interp, tuple((k.t, k.value, k.handles) for k in tr.keys))
                                 for ch, tr in self.tracks.items()))

    def _restore(self, state: State) -> None:
        self.name = state[0]
        self.tracks = {ch: Track(interp, [Key(t, v, h) for t, v, h in keys]) for ch, interp, keys in state[1]}
        self._saved = state
        self.version += 1
        self._curves = None

    @property
    def can_undo(self) -> bool:
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        return bool(self._redo)

    def undo(self) -> bool:
        """Go back one edit; False when there is none."""
        if not self._undo:
            return False
        self._redo.append(self._saved)
        self._restore(self._undo.pop())
        return True

    def redo(self) -> bool:
        """Repeat the edit last undone; False when there is none."""
        if not self._redo:
            return False
        self._undo.append(self._saved)
        self._restore(self._redo.pop())
        return True

    @contextlib.contextmanager
    def batch(self) -> Iterator[None]:
        """Edits inside are one undo step."""
        self._batch += 1
        try:
            yield
        finally:
            self._batch -= 1
            if self._batch == 0:
                self._record()

    def _record(self) -> None:
        state = self._state()
        if state != self._saved:
            self._undo.append(self._saved)
            del self._undo[:-UNDO_DEPTH]
            self._redo.clear()
            self._saved = state

    # ------------------------------------------------------------------ edits
    def _changed(self) -> None:
        self.version += 1
        self._curves = None
        if self._batch == 0:
            self._record()

    def rename(self, name: str) -> None:
        self.name = check_name(name)
        self._changed()

    def set_key(self, channel: str, t: float, value: float, interp: str | None = None) -> None:
        """Add a key (or replace the key at the same time) on ``channel``; ``interp`` sets the channel's."""
        if not math.isfinite(t) or t < 0:
            raise ClipError(f"key time must be a finite number >= 0 s, got {t!r}")
        if not math.isfinite(value):
            raise ClipError(f"key value for {channel!r} must be finite, got {value!r}")
        track = self.tracks.setdefault(channel, Track())
        if interp is not None:
            self._set_interp(track, interp)
        for k in track.keys:
            if abs(k.t - t) <= TIME_EPS:
                k.value = float(value)
                break
        else:
            track.keys.append(Key(float(t), float(value)))
            track.keys.sort(key=lambda k: k.t)
        self._changed()

    def remove_key(self, channel: str, t: float) -> bool:
        """Remove the key of ``channel`` at time ``t``; a channel left without keys leaves the clip."""
        track = self.tracks.get(channel)
        if track is None:
            return False
        before = len(track.keys)
        track.keys = [k for k in track.keys if abs(k.t - t) > TIME_EPS]
        if not track.keys:
            del self.tracks[channel]
        removed = len(track.keys) != before
        if removed:
            self._changed()
        return removed

    def move_key(self, channel: str, index: int, t: float, value: float) -> int:
        """Move key ``index`` of ``channel`` to time ``t`` and ``value``; returns its index after the move (keys stay
        sorted). Refused when another key of the channel already sits at ``t``."""
        track, key = self._key(channel, index)
        if not math.isfinite(t) or t < 0:
            raise ClipError(f"key time must be a finite number >= 0 s, got {t!r}")
        if not math.isfinite(value):
            raise ClipError(f"key value for {channel!r} must be finite, got {value!r}")
        for other in track.keys:
            if other is not key and abs(other.t - t) <= TIME_EPS:
                raise ClipError(f"{channel!r} already has a key at {t:.3f} s: delete it first or choose another time")
        key.t, key.value = float(t), float(value)
        track.keys.sort(key=lambda k: k.t)
        self._changed()
        return track.keys.index(key)

    def handles(self, channel: str, index: int) -> tuple[float, float, float, float]:
        """Key ``index``'s Bezier handles (in_dt, in_dv, out_dt, out_dv) as the clip uses them (auto or set)."""
        track, _ = self._key(channel, index)
        if track.interp != "bezier":
            raise ClipError(f"channel {channel!r} is {track.interp}, not bezier: its keys have no handles")
        row = track.rows()[index]
        return (row[2], row[3], row[4], row[5])

    def set_handles(self, channel: str, index: int, handles: tuple[float, float, float, float]) -> None:
        """Set key ``index``'s Bezier handles (in_dt <= 0 <= out_dt, as the clip schema requires); they stay as set
        when neighbouring keys move."""
        track, key = self._key(channel, index)
        if track.interp != "bezier":
            raise ClipError(f"channel {channel!r} is {track.interp}, not bezier: set its interpolation to bezier first")
        h = tuple(float(x) for x in handles)
        if len(h) != 4 or not all(math.isfinite(x) for x in h):
            raise ClipError(f"handles must be four finite numbers (in_dt, in_dv, out_dt, out_dv), got {handles!r}")
        if h[0] > 0 or h[2] < 0:
            raise ClipError(f"handles need in_dt <= 0 <= out_dt (got in_dt={h[0]!r}, out_dt={h[2]!r})")
        key.handles = (h[0], h[1], h[2], h[3])
        self._changed()

    def _key(self, channel: str, index: int) -> tuple[Track, Key]:
        track = self.tracks.get(channel)
        if track is None:
            raise ClipError(f"channel {channel!r} has no keys in clip {self.name!r}")
        if not 0 <= index < len(track.keys):
            raise ClipError(f"channel {channel!r} has {len(track.keys)} key(s): no key #{index + 1}")
        return track, track.keys[index]

    def set_interp(self, channel: str, interp: str) -> None:
        track = self.tracks.get(channel)
        if track is None:
            raise ClipError(f"channel {channel!r} has no keys in clip {self.name!r}")
        self._set_interp(track, interp)
        self._changed()

    @staticmethod
    def _set_interp(track: Track, interp: str) -> None:
        if interp not in INTERPS:
            raise ClipError(f"interpolation must be one of {', '.join(INTERPS)}, got {interp!r}")
        if interp != track.interp:
            for k in track.keys:
                k.handles = None
        track.interp = interp

    def clear(self) -> None:
        self.tracks.clear()
        self._changed()

    # ------------------------------------------------------------------ reading
    @property
    def duration(self) -> float:
        return max((t.keys[-1].t for t in self.tracks.values() if t.keys), default=0.0)

    def key_times(self, channel: str) -> list[float]:
        track = self.tracks.get(channel)
        return [k.t for k in track.keys] if track else []

    def curves(self) -> dict[str, Curve]:
        if self._curves is None:
            self._curves = {ch: make_curve(tr.interp, tr.rows(), f"clip {self.name!r}.channels.{ch}")
                            for ch, tr in self.tracks.items() if tr.keys}
        return self._curves

    def sample(self, t: float) -> dict[str, float]:
        """Every keyed channel's value at clip time ``t`` (as the daemon's timeline evaluates it)."""
        return {ch: c.value(t) for ch, c in self.curves().items()}

    # ------------------------------------------------------------------ protocol JSON
    def to_dict(self) -> dict[str, Any]:
        """The protocol's clip map (``load_clip``'s ``clip``); a clip needs at least one keyed channel."""
        if not self.tracks:
            raise ClipError(f"clip {self.name!r} has no keys yet")
        return {"name": self.name,
                "channels": {ch: {"interp": tr.interp, "keys": tr.rows()} for ch, tr in sorted(self.tracks.items())}}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_dict(cls, data: Any, where: str = "clip") -> ClipDoc:
        """A document from a protocol clip map (validated as the daemon validates it)."""
        try:
            clip_from_dict(data, where)
        except ValueError as exc:
            raise ClipError(str(exc)) from None
        doc = cls(data["name"])
        for ch, spec in data["channels"].items():
            interp = spec.get("interp", "linear")
            keys = [Key(float(r[0]), float(r[1]), tuple(float(x) for x in r[2:6]) if interp == "bezier" else None)
                    for r in spec["keys"]]
            doc.tracks[ch] = Track(interp, keys)
        doc._changed()
        doc._undo.clear()  # a document read from a file starts its own history
        return doc

    @classmethod
    def from_json(cls, text: str | bytes, where: str = "clip") -> ClipDoc:
        try:
            data = json.loads(text)
        except (ValueError, UnicodeDecodeError) as exc:
            raise ClipError(f"{where}: not JSON: {exc}") from None
        return cls.from_dict(data, where)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(self.to_json() + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> ClipDoc:
        path = Path(path)
        return cls.from_json(path.read_bytes(), str(path))

    def check_channels(self, known: Mapping[str, object]) -> None:
        """Refuse channels the head does not have (naming them)."""
        unknown = sorted(ch for ch in self.tracks if ch not in known)
        if unknown:
            raise ClipError(f"clip {self.name!r}: channel(s) not on this head: {', '.join(unknown)}")


def check_name(name: str) -> str:
    if not isinstance(name, str) or not 1 <= len(name) <= 128 or not name.strip():
        raise ClipError(f"clip name must be 1..128 characters, got {name!r}")
    return name
