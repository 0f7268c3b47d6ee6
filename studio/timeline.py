"""The multi-track timeline chart: every keyed channel of a clip as one row, its keys, the selected key and the
playhead, as uPlot data and series for viser's chart.

Each track occupies a row of height 1 (the first track on top); its curve is drawn within the row from the channel's
lower limit (row bottom + 0.1) to its upper limit (row top - 0.1), so channels of different units share one chart.
The playhead is a vertical line: its time appears twice in the x values, once at the chart's bottom and once at the
top (uPlot draws a series in the order of its points).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from studio.clipdoc import ClipDoc

#: Colours of the tracks, in turn.
TRACK_COLORS = ("#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f")
KEY_COLOR = "#d62728"
SELECTED_COLOR = "#ff7f0e"
PLAYHEAD_COLOR = "#444444"
#: Curve samples over the clip's length (key times are added to them).
SAMPLES = 200


@dataclass(frozen=True)
class Chart:
    """uPlot data (x first), series and scales for :class:`viser.GuiUplotHandle`, and the tracks top to bottom."""

    data: tuple[np.ndarray, ...]
    series: tuple[dict, ...]
    tracks: tuple[str, ...]

    @property
    def scales(self) -> dict:
        """A fixed height (one unit per row): uPlot's automatic range would fail on the key series, which are NaN
        (gaps) away from their keys."""
        return {"x": {"time": False}, "y": {"auto": False, "range": [0.0, float(max(len(self.tracks), 1))]}}


def track_order(doc: ClipDoc, channel_order: tuple[str, ...]) -> tuple[str, ...]:
    """The clip's keyed channels in the head's channel order (channels the head lacks last, by name)."""
    rank = {name: i for i, name in enumerate(channel_order)}
    return tuple(sorted(doc.tracks, key=lambda ch: (rank.get(ch, len(rank)), ch)))


def row_y(value: np.ndarray | float, row: int, n_rows: int, lo: float, hi: float) -> np.ndarray:
    """Chart height of ``value`` on track ``row`` (0 = top) of ``n_rows``, with the channel's range [lo, hi]."""
    span = hi - lo if hi > lo else 1.0
    frac = np.clip((np.asarray(value, dtype=np.float64) - lo) / span, 0.0, 1.0)
    return (n_rows - 1 - row) + 0.1 + 0.8 * frac


def timeline_chart(doc: ClipDoc, ranges: Mapping[str, tuple[float, float]], channel_order: tuple[str, ...],
                   end: float, playhead: float, selected: tuple[str, int] | None = None) -> Chart:
    """The chart of ``doc`` over [0, ``end``] s with the playhead at ``playhead`` s and key ``selected`` (channel,
    index) marked. ``ranges`` gives each channel's (min, max) in its unit."""
    if not end > 0:
        raise ValueError(f"timeline length must be > 0 s, got {end!r}")
    tracks = track_order(doc, channel_order)
    n = max(len(tracks), 1)
    times = [k.t for ch in tracks for k in doc.tracks[ch].keys]
    x = np.union1d(np.linspace(0.0, end, SAMPLES), np.asarray(times, dtype=np.float64))
    t_play = float(np.clip(playhead, 0.0, end))
    at = int(np.searchsorted(x, t_play))
    x = np.insert(x, at, [t_play, t_play])  # the playhead's two points
    curves = doc.curves()
    data: list[np.ndarray] = [x]
    series: list[dict] = [{"label": "t (s)"}]
    for row, ch in enumerate(tracks):
        lo, hi = ranges.get(ch, (0.0, 1.0))
        color = TRACK_COLORS[row % len(TRACK_COLORS)]
        values = np.array([curves[ch].value(float(t)) for t in x])
        data.append(row_y(values, row, n, lo, hi))
        series.append({"label": ch, "stroke": color, "width": 2})
        keys = np.full(len(x), np.nan)
        for k in doc.tracks[ch].keys:
            keys[int(np.argmin(np.abs(x - k.t)))] = row_y(k.value, row, n, lo, hi)
        data.append(keys)
        series.append({"label": f"{ch} keys", "stroke": KEY_COLOR, "width": 0, "points": {"show": True, "size": 7}})
    sel = np.full(len(x), np.nan)
    if selected is not None and selected[0] in doc.tracks and 0 <= selected[1] < len(doc.tracks[selected[0]].keys):
        ch, i = selected
        k = doc.tracks[ch].keys[i]
        lo, hi = ranges.get(ch, (0.0, 1.0))
        sel[int(np.argmin(np.abs(x - k.t)))] = row_y(k.value, tracks.index(ch), n, lo, hi)
    data.append(sel)
    series.append({"label": "selected key", "stroke": SELECTED_COLOR, "width": 0,
                   "points": {"show": True, "size": 13, "fill": SELECTED_COLOR}})
    head = np.full(len(x), np.nan)
    head[at], head[at + 1] = 0.0, float(n)
    data.append(head)
    series.append({"label": "playhead", "stroke": PLAYHEAD_COLOR, "width": 1.5, "spanGaps": False})
    return Chart(tuple(data), tuple(series), tracks)
