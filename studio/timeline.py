"""The timeline's content for the page's editor: every keyed channel as a track with its keys, Bezier handles and
curve, the playhead, the selected key, the audio and what undo and redo can do, as one JSON-ready map.

The page (``static/timeline.js``) draws each track in a row of its own, from the channel's lower limit at the row's
bottom to its upper limit at the top, so channels of different units share one view; keys and handles are dragged
there and sent back as edits. Curves are sampled here with the clip's own evaluation (``models.clip``), so what the
page draws is what the daemon plays; the key times are among the samples, so every key lies on its curve.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from studio.clipdoc import ClipDoc

#: Curve samples over the timeline's length (key times are added to them).
SAMPLES = 240


@dataclass(frozen=True)
class Audio:
    """The sound loaded in the page: its file name and length (s)."""

    name: str
    duration: float


def track_order(doc: ClipDoc, channel_order: tuple[str, ...]) -> tuple[str, ...]:
    """The clip's keyed channels in the head's channel order (channels the head lacks last, by name)."""
    rank = {name: i for i, name in enumerate(channel_order)}
    return tuple(sorted(doc.tracks, key=lambda ch: (rank.get(ch, len(rank)), ch)))


def timeline_length(doc: ClipDoc, length: float, audio: Audio | None) -> float:
    """The span the timeline shows (s): the clip's set length, its last key and the audio, whichever is longest."""
    return max(float(length), doc.duration, audio.duration if audio else 0.0, 0.1)


def timeline_state(doc: ClipDoc, ranges: Mapping[str, tuple[float, float]], channel_order: tuple[str, ...],
                   length: float, playhead: float, selected: tuple[str, int] | None = None,
                   audio: Audio | None = None) -> dict[str, Any]:
    """The map the page's timeline draws: ``tracks`` top to bottom, each with ``name``, ``interp``, ``lo``/``hi``
    (the channel's range), ``keys`` (rows as in the clip schema, Bezier ones with their handles as the clip uses
    them) and ``curve`` (``t`` and ``v`` samples); ``length``, ``playhead``, ``selected``, ``audio``, ``can_undo``,
    ``can_redo`` and the document's ``version``."""
    end = timeline_length(doc, length, audio)
    tracks = []
    curves = doc.curves()
    for ch in track_order(doc, channel_order):
        tr = doc.tracks[ch]
        lo, hi = ranges.get(ch, (0.0, 1.0))
        x = np.union1d(np.linspace(0.0, end, SAMPLES), [k.t for k in tr.keys])
        curve = curves[ch]
        tracks.append({"name": ch, "interp": tr.interp, "lo": float(lo), "hi": float(hi), "keys": tr.rows(),
                       "curve": {"t": [float(t) for t in x], "v": [curve.value(float(t)) for t in x]}})
    sel = None
    if selected is not None and selected[0] in doc.tracks and 0 <= selected[1] < len(doc.tracks[selected[0]].keys):
        sel = [selected[0], selected[1]]
    return {"version": doc.version, "name": doc.name, "length": end, "playhead": float(playhead), "selected": sel,
            "tracks": tracks, "audio": {"name": audio.name, "duration": audio.duration} if audio else None,
            "can_undo": doc.can_undo, "can_redo": doc.can_redo}
