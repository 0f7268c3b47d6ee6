"""Clips compiled to flat numpy arrays, for the control core to evaluate every cycle.

:class:`CompiledClip` holds every channel's keys as *slots* in flat arrays, so :meth:`CompiledClip.sample` evaluates
every channel with a fixed number of numpy calls (no per-channel Python loop). The per-channel key search is one
``searchsorted`` over integer codes ``curve * M + rank(t) + 1``, ``rank`` being a key time's index among all the
clip's distinct key times: exact, whatever the times. Step and linear values are the bits of
:meth:`models.clip.Clip.sample`; Bezier channels run the safeguarded Newton iteration of
:func:`models.clip._bezier_eval`, compiled (:mod:`models._cycle_kernels`) where numba is installed, else in numpy on
all of them in lockstep, each stopping where the scalar loop stops (a few numpy calls per iteration): the same bits
either way. Everything is plain numpy arrays and strings: picklable and cheap to hand to another process.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.clip import Clip, ClipError
from models.kernel_args import bezier_sample_example, channel_targets_example, following_watch_example
from models.kernel_support import kernels_available
from models.kernels_aot import kernel
from runtime.messages import ClipSpec

_NEWTON_STEPS = 24  # as models.clip._bezier_eval
_NEWTON_TOL = 1e-10


@dataclass(frozen=True, eq=False)
class CompiledClip:
    """A clip's curves as flat arrays over the columns ``channel_index``; build it with :func:`compile_clip`.

    Each curve (a channel with keys, in column order) owns a run of slots: a hold slot (its first value, before its
    first key), then one per key. Slot ``k`` is stored at index ``k + 1`` of the ``slot_*`` arrays, so the index
    ``searchsorted`` returns addresses the slot before it: key time ``slot_t``, time to the next key ``slot_dt`` (1
    where the value holds: hold slots, last keys), value ``slot_v`` and change to the next key ``slot_dv`` (0 for
    step and Bezier keys and where the value holds). ``slot_code`` is ``curve * M + rank + 1`` per key slot
    (``curve * M`` for hold slots), ``rank`` a time's index in ``grid``, the sorted distinct key times;
    ``code_base`` is ``curve * M + 1``; ``column`` each curve's column. Bezier curves (``bez``: curve numbers) keep
    per slot the power-basis cubic coefficients of time and value in the segment parameter (``bez_coef``, row =
    slot index + ``bez_row``) and their first and last key times (``bez_first``, ``bez_last``).
    """

    name: str
    channel_index: tuple[str, ...]
    duration: float
    key_count: int
    grid: np.ndarray
    slot_code: np.ndarray
    slot_t: np.ndarray
    slot_dt: np.ndarray
    slot_v: np.ndarray
    slot_dv: np.ndarray
    column: np.ndarray
    code_base: np.ndarray
    bez: np.ndarray
    bez_row: np.ndarray
    bez_first: np.ndarray
    bez_last: np.ndarray
    bez_coef: np.ndarray

    @property
    def nbytes(self) -> int:
        """Bytes held in arrays."""
        return sum(v.nbytes for v in vars(self).values() if isinstance(v, np.ndarray))

    def sample(self, t: float, out: np.ndarray, compiled: bool | None = None) -> None:
        """Write every channel's value at clip time ``t`` into ``out`` (one float64 per column; NaN for columns the
        clip has no curve for). Values hold before a curve's first key and after its last, as
        :meth:`models.clip.Curve.value`. ``t`` must be finite. Bezier channels run the compiled kernel
        (:mod:`models._cycle_kernels`) where numba is installed, else the numpy lockstep iteration (``compiled``
        chooses; both give the bits of :meth:`models.clip.Clip.sample`)."""
        if len(out) != len(self.channel_index):
            raise ValueError(f"out has {len(out)} entries; the clip is compiled for {len(self.channel_index)} channels")
        t = float(t)
        r = self.grid.searchsorted(t, "right")  # distinct key times <= t
        i = self.slot_code.searchsorted(self.code_base + r)  # per curve: 1 + its last slot at or before t
        u = t - self.slot_t.take(i)
        u /= self.slot_dt.take(i)
        nbez = len(self.bez)
        if nbez:
            if compiled is None:
                compiled = kernels_available()
            if not compiled:
                guess = u.copy() if nbez == len(u) else u.take(self.bez)
        u *= self.slot_dv.take(i)  # v0 + u (v1 - v0): the bits of Curve.value
        direct = len(self.column) == len(out)
        np.add(u, self.slot_v.take(i), out=out if direct and not nbez else u)
        if nbez:
            if compiled:
                kernel("bezier_sample")(t, i, self.bez, self.bez_row, self.bez_first, self.bez_last, self.bez_coef,
                                        self.slot_t, self.slot_dt, u)
            else:
                self._bezier(t, i if nbez == len(u) else i.take(self.bez), guess, u)
            if direct:
                out[:] = u
        if not direct:
            out.fill(np.nan)
            out[self.column] = u

    def _bezier(self, t: float, i: np.ndarray, s: np.ndarray, vals: np.ndarray) -> None:
        """Overwrite the Bezier curves' entries of ``vals`` strictly inside their key range: the steps of
        :func:`models.clip._bezier_eval` (safeguarded Newton on x(s) = t from ``s``, then y(s)), all curves in
        lockstep, each stopping where the scalar loop would. ``i``: the Bezier curves' slot indices."""
        inside = self.bez_first < t
        inside &= self.bez_last > t
        if not inside.any():
            return
        i = i + self.bez_row
        xa, xb, xc, xd, ya, yb, yc, yd = self.bez_coef.take(i, axis=0).T
        x = _cubic(xa, xb, xc, xd, s)
        x -= t
        active = inside & (np.abs(x) >= _NEWTON_TOL)
        if active.any():
            lo, hi = np.zeros_like(s), np.ones_like(s)
            xa3, xb2 = 3 * xa, 2 * xb
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                for step in range(1, _NEWTON_STEPS + 1):
                    # lo and hi of curves already stopped go stale: their s no longer changes.
                    pos = x > 0
                    hi = np.where(pos, s, hi)
                    lo = np.where(pos, lo, s)
                    dx = _cubic(0.0, xa3, xb2, xc, s)
                    mid = lo + hi
                    mid *= 0.5
                    s_new = np.where(dx > 1e-12, s - x / dx, mid)
                    s = np.where(active, np.where((lo < s_new) & (s_new < hi), s_new, mid), s)
                    if step == _NEWTON_STEPS:
                        break
                    x = _cubic(xa, xb, xc, xd, s)
                    x -= t
                    active &= np.abs(x) >= _NEWTON_TOL  # x is finite: s stays in [0, 1]
                    if not active.any():
                        break
        y = _cubic(ya, yb, yc, yd, s)
        if len(self.bez) == len(vals) and inside.all():
            vals[:] = y
        else:
            vals[self.bez[inside]] = y[inside]


def prepare_kernels() -> None:
    """Load the compiled kernels of the cycle's own stages (the Bezier sampling here, the core's following-error
    watch and channel mapping; the ahead-of-time module, else numba's JIT) before the loop starts: their first call
    in a cycle would otherwise load a shared library or compile. Nothing to do without numba."""
    if kernels_available():
        kernel("bezier_sample")(*bezier_sample_example())
        kernel("following_watch")(*following_watch_example())
        kernel("channel_targets")(*channel_targets_example())


def _cubic(a: np.ndarray | float, b: np.ndarray, c: np.ndarray, d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """((a s + b) s + c) s + d, in that order of operations (a = 0.0: (b s + c) s + d)."""
    if isinstance(a, float):
        v = b * s
    else:
        v = a * s
        v += b
        v *= s
    v += c
    v *= s
    v += d
    return v


def compile_clip(clip: Clip | ClipSpec, channels: Sequence[str]) -> CompiledClip:
    """Compile ``clip`` for the columns ``channels`` (in that order; columns without a curve sample as NaN).

    A validated :class:`~runtime.messages.ClipSpec` compiles without per-key Python objects; a
    :class:`~models.clip.Clip` reuses its curves' Bezier segments. A clip channel not in ``channels`` is a
    :class:`~models.clip.ClipError`.
    """
    channels = tuple(channels)
    if len(set(channels)) != len(channels):
        raise ClipError(f"compile_clip: channels list a name twice: {sorted(channels)}")
    names = list(clip.channels)
    missing = [ch for ch in names if ch not in channels]
    if missing:
        raise ClipError(f"clip {clip.name!r}: channel(s) {sorted(missing)[:8]} not among the compiled channels")
    curves = []  # (column, interp, times, values, bezier segment coefficients or None)
    for col, ch in enumerate(channels):
        if ch not in clip.channels:
            continue
        if isinstance(clip, ClipSpec):
            interp = clip.channels[ch].interp
            keys = clip.key_array(ch)
            times, values = keys[:, 0], keys[:, 1]
            seg = _bezier_segments(keys) if interp == "bezier" else None
        else:
            curve = clip.channels[ch]
            interp = curve.interp
            times, values = np.array(curve.times, np.float64), np.array(curve.values, np.float64)
            seg = np.array(curve._seg, np.float64).reshape(-1, 8) if interp == "bezier" else None
        curves.append((col, interp, times, values, seg))
    return _build(clip.name, channels, curves)


def _build(name: str, channels: tuple[str, ...], curves: list) -> CompiledClip:
    """Slots of every curve (see :class:`CompiledClip`) from (column, interp, times, values, Bezier segments)."""
    n = np.array([len(c[2]) for c in curves], np.int64)
    slot0 = np.concatenate([[0], np.cumsum(n + 1)[:-1]]).astype(np.int64)  # each curve's hold slot
    grid = np.unique(np.concatenate([c[2] for c in curves]))
    m = len(grid) + 1
    if len(curves) * m >= 2**62:
        raise ClipError(f"clip {name!r}: too many keys to compile")
    total = int((n + 1).sum())
    slot_t, slot_v = np.zeros(total + 1), np.zeros(total + 1)  # index 0 is a pad: slot k lives at k + 1
    slot_dt, slot_dv = np.ones(total + 1), np.zeros(total + 1)
    slot_code = np.empty(total, np.int64)
    rows: list[np.ndarray] = []
    bez, bez_row, bez_span = [], [], []
    for k, (_, interp, times, values, seg) in enumerate(curves):
        a = slot0[k] + 1  # index of the hold slot
        slot_t[a], slot_v[a] = times[0], values[0]
        slot_t[a + 1:a + 1 + n[k]], slot_v[a + 1:a + 1 + n[k]] = times, values
        slot_dt[a + 1:a + n[k]] = np.diff(times)
        if interp == "linear":
            slot_dv[a + 1:a + n[k]] = np.diff(values)
        slot_code[slot0[k]] = k * m
        slot_code[slot0[k] + 1:slot0[k] + 1 + n[k]] = k * m + 1 + grid.searchsorted(times)
        if interp == "bezier":
            bez.append(k)
            bez_span.append((times[0], times[-1]))
            bez_row.append(sum(len(r) for r in rows) - a)  # the hold slot (index a) is the curve's first row
            rows.append(np.vstack([np.zeros((1, 8)), seg.reshape(-1, 8), np.zeros((1, 8))]))
    arrays = {"grid": grid, "slot_code": slot_code, "slot_t": slot_t, "slot_dt": slot_dt, "slot_v": slot_v,
              "slot_dv": slot_dv, "column": np.array([c[0] for c in curves], np.int64),
              "code_base": np.arange(len(curves), dtype=np.int64) * m + 1, "bez": np.array(bez, np.int64),
              "bez_row": np.array(bez_row, np.int64), "bez_first": np.array([b[0] for b in bez_span], np.float64),
              "bez_last": np.array([b[1] for b in bez_span], np.float64),
              "bez_coef": np.vstack(rows) if rows else np.zeros((0, 8))}
    for arr in arrays.values():
        arr.flags.writeable = False
    duration = max(float(c[2][-1]) for c in curves)
    return CompiledClip(name, channels, duration, int(n.sum()), **arrays)


def _bezier_segments(keys: np.ndarray) -> np.ndarray:
    """Per segment the cubic coefficients (time a, b, c, d, value a, b, c, d) of :func:`models.clip.make_curve`
    for keys ``[t, v, in_dt, in_dv, out_dt, out_dv]``, with the same arithmetic (and so the same bits)."""
    a, b = keys[:-1], keys[1:]
    span = b[:, 0] - a[:, 0]
    with np.errstate(divide="ignore", over="ignore"):
        fo = np.where(a[:, 4] > 0, np.minimum(1.0, span / a[:, 4]), 1.0)
        fi = np.where(b[:, 2] < 0, np.minimum(1.0, span / -b[:, 2]), 1.0)
    out = np.empty((len(a), 8))
    for k, (p0, d1, p3, d2) in enumerate(((a[:, 0], a[:, 4], b[:, 0], b[:, 2]), (a[:, 1], a[:, 5], b[:, 1], b[:, 3]))):
        p1 = p0 + d1 * fo
        p2 = p3 + d2 * fi
        out[:, 4 * k] = -p0 + 3 * p1 - 3 * p2 + p3
        out[:, 4 * k + 1] = 3 * p0 - 6 * p1 + 3 * p2
        out[:, 4 * k + 2] = -3 * p0 + 3 * p1
        out[:, 4 * k + 3] = p0
    return out
