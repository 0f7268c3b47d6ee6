"""MIDI timecode: mido's quarter-frame and full-frame (sysex) messages ↔ timecode samples (pure; no ports).

Quarter frames carry a timecode in eight pieces over two frames (piece 0: frames low nibble ... piece 7: hours high
bit and the rate code); a complete forward sequence gives one sample as of the arrival of piece 7, that is the
encoded frame plus 7/4 frames. A full-frame message (``F0 7F <device> 01 01 hh mm ss ff F7``) is a locate. Frame
arithmetic, drop-frame 29.97 included, is the ``timecode`` library's. The same module builds the messages a timecode
generator sends (tests, examples, the benchmark).
"""

from __future__ import annotations

from dataclasses import dataclass

import mido
from timecode import Timecode

from runtime.inputs.config import RATES

#: MTC rate code (bits 5-6 of the hours byte) → rate name (the ``timecode`` library's) and back.
RATE_CODES = {0: "24", 1: "25", 2: "29.97", 3: "30"}
CODE_OF = {v: k for k, v in RATE_CODES.items()}


@dataclass(frozen=True)
class TimecodeSample:
    """Timecode ``seconds`` as of arrival time ``received``; ``label``: hh:mm:ss:ff (``;ff`` drop frame)."""

    seconds: float
    fps: float
    rate: str  # "24", "25", "29.97df", "30"
    label: str
    full: bool
    received: float


class MtcError(ValueError):
    """A message that is no valid timecode (the reason is the message)."""


def _tc(rate: str, hh: int, mm: int, ss: int, ff: int) -> Timecode:
    if hh > 23 or mm > 59 or ss > 59 or ff >= round(RATES[rate]):
        raise MtcError(f"timecode {hh:02d}:{mm:02d}:{ss:02d}:{ff:02d} is out of range at {rate} fps")
    if rate == "29.97" and ss == 0 and ff < 2 and mm % 10 != 0:
        raise MtcError(f"frame {hh:02d}:{mm:02d}:{ss:02d};{ff:02d} does not exist in 29.97 drop frame")
    sep = ";" if rate == "29.97" else ":"
    return Timecode(rate, f"{hh:02d}:{mm:02d}:{ss:02d}{sep}{ff:02d}")


def _sample(rate: str, hh: int, mm: int, ss: int, ff: int, extra_frames: float, full: bool,
            now: float) -> TimecodeSample:
    tc = _tc(rate, hh, mm, ss, ff)
    fps = RATES[rate]
    return TimecodeSample((tc.frame_number + extra_frames) / fps, fps, "29.97df" if rate == "29.97" else rate,
                          str(tc), full, now)


class MtcAssembler:
    """Collects quarter frames into samples; takes full-frame messages as locates."""

    def __init__(self) -> None:
        self.pieces: list[int] = []

    def feed(self, msg: mido.Message, now: float) -> TimecodeSample | None:
        """A sample when ``msg`` completes one (piece 7 of a forward sequence, or a full frame); None otherwise;
        :class:`MtcError` for a message that is not timecode or not valid."""
        if msg.type == "quarter_frame":
            kind, value = msg.frame_type, msg.frame_value
            if kind == 0:
                self.pieces = [value]
                return None
            if len(self.pieces) != kind:  # a piece out of sequence: start over at the next piece 0
                self.pieces = []
                return None
            self.pieces.append(value)
            if kind < 7:
                return None
            p, self.pieces = self.pieces, []
            rate = RATE_CODES[(p[7] >> 1) & 0x3]
            return _sample(rate, ((p[7] & 1) << 4) | p[6], ((p[5] & 0x3) << 4) | p[4], ((p[3] & 0x3) << 4) | p[2],
                           ((p[1] & 1) << 4) | p[0], 7 / 4, False, now)
        if msg.type == "sysex":
            d = msg.data
            if len(d) == 8 and d[0] == 0x7F and d[2] == 0x01 and d[3] == 0x01:
                rate = RATE_CODES[(d[4] >> 5) & 0x3]
                return _sample(rate, d[4] & 0x1F, d[5], d[6], d[7], 0, True, now)
            raise MtcError("a sysex message that is no MTC full frame")
        raise MtcError(f"a {msg.type} message is no timecode")


def _fields(frame: int, rate: str) -> tuple[int, int, int, int]:
    tc = Timecode(rate, frames=frame + 1)
    return tc.hrs, tc.mins, tc.secs, tc.frs


def quarter_frames(frame: int, rate: str) -> list[mido.Message]:
    """The eight quarter-frame messages that encode frame number ``frame`` (0-based) at ``rate``; a generator
    sends one every quarter frame, a sequence every two frames."""
    hh, mm, ss, ff = _fields(frame, rate)
    code = CODE_OF[rate]
    values = [ff & 0xF, ff >> 4, ss & 0xF, ss >> 4, mm & 0xF, mm >> 4, hh & 0xF, (hh >> 4) | (code << 1)]
    return [mido.Message("quarter_frame", frame_type=k, frame_value=v) for k, v in enumerate(values)]


def full_frame(frame: int, rate: str) -> mido.Message:
    """The full-frame (locate) message of frame number ``frame`` at ``rate``."""
    hh, mm, ss, ff = _fields(frame, rate)
    return mido.Message("sysex", data=[0x7F, 0x7F, 0x01, 0x01, (CODE_OF[rate] << 5) | hh, mm, ss, ff])


def frame_of(seconds: float, rate: str) -> int:
    """The frame number at ``seconds`` of timecode."""
    return int(seconds * RATES[rate] + 1e-9)
