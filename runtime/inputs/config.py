"""The ``[inputs]`` tables of a head spec, validated against the head's channels (``docs/show_control.md``).

Types and unknown keys are checked by :mod:`models.headschema`; here the values: addresses (loopback unless the
input's ``allow_remote``), channels the head knows, DMX slots inside the universe, frame rates and chase offsets.
Errors are :class:`~models.errors.SpecError`s naming the file and key.
"""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass

import msgspec

from models import headschema as S
from models.errors import SpecError
from models.headspec import HeadSpec
from runtime.core.channels import ChannelMap, UnknownChannel
from runtime.core.chase import ChaseParams

#: MTC rate codes and the ``timecode`` library's names of the four MIDI timecode rates.
RATES = {"24": 24.0, "25": 25.0, "29.97": 30000 / 1001, "30": 30.0}
DMX_SLOTS = 512


@dataclass(frozen=True)
class OscConfig:
    host: str
    port: int
    tcp: tuple[str, int] | None
    map: tuple[tuple[str, str], ...]  # (address pattern, channel or channel pattern with one "*")
    control_prefix: str
    control_allow: tuple[str, ...]
    watchdog: bool


@dataclass(frozen=True)
class SlotMap:
    """A channel fed by DMX slot ``index`` (0-based in the universe; 16-bit: it and the next, coarse first)."""

    channel: str
    index: int
    bits: int
    lo: float
    hi: float


@dataclass(frozen=True)
class SacnConfig:
    host: str
    port: int
    universe: int
    slots: tuple[SlotMap, ...]
    merge: str
    source_timeout_s: float
    multicast: bool


@dataclass(frozen=True)
class TimecodeConfig:
    bind: tuple[str, int] | None
    midi_port: str | None
    rate: str
    chase: ChaseParams


@dataclass(frozen=True)
class InputsConfig:
    osc: OscConfig | None = None
    sacn: SacnConfig | None = None
    timecode: TimecodeConfig | None = None

    @property
    def any(self) -> bool:
        return self.osc is not None or self.sacn is not None or self.timecode is not None


def inputs_config(head: HeadSpec, channels: ChannelMap) -> InputsConfig:
    """The head's ``[inputs]``, validated (an empty :class:`InputsConfig` when it has none)."""
    raw = head.section("inputs")
    source = str(head.source)
    if not raw:
        return InputsConfig()
    tables = msgspec.convert(dict(raw), S.InputsTable, strict=True)
    osc = sacn = tc = None
    if tables.osc is not None:
        osc = _osc(msgspec.convert(tables.osc, S.OscTable, strict=True), channels, source)
    if tables.sacn is not None:
        sacn = _sacn(msgspec.convert(tables.sacn, S.SacnTable, strict=True), head, channels, source)
    if tables.timecode is not None:
        tc = _timecode(msgspec.convert(tables.timecode, S.TimecodeTable, strict=True), source)
    return InputsConfig(osc, sacn, tc)


def parse_hostport(text: str, key: str, source: str, allow_remote: bool, default_port: int | None = None
                   ) -> tuple[str, int]:
    """``"host:port"`` → (host, port); loopback only unless ``allow_remote``."""
    host, sep, port_text = text.rpartition(":")
    if not sep:
        if default_port is None:
            raise SpecError(source, key, "must be HOST:PORT", text)
        host, port_text = text, str(default_port)
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise SpecError(source, key, "has a bad port (0-65535)", text)
    check_host(host, key, source, allow_remote)
    return host, int(port_text)


def check_host(host: str, key: str, source: str, allow_remote: bool) -> None:
    if host == "localhost":
        return
    try:
        addr = ipaddress.ip_address(host)
    except ValueError:
        raise SpecError(source, key, "must be an IP address (or localhost)", host) from None
    if not addr.is_loopback and not allow_remote:
        raise SpecError(source, key, "binds beyond loopback; set allow_remote = true in the same table to allow "
                        "it", host)


def _osc(t: S.OscTable, channels: ChannelMap, source: str) -> OscConfig:
    host, port = parse_hostport(t.bind, "inputs.osc.bind", source, t.allow_remote)
    tcp = None if t.tcp is None else parse_hostport(t.tcp, "inputs.osc.tcp", source, t.allow_remote)
    pairs = []
    for address, channel in t.map.items():
        key = f"inputs.osc.map.{address!r}"
        if not address.startswith("/"):
            raise SpecError(source, key, "an OSC address starts with '/'", address)
        if channel.count("*") > 1 or ("*" in channel) != ("*" in address):
            raise SpecError(source, key, "a '*' in the address needs exactly one '*' in the channel (the part the "
                            "address's '*' matched)", channel)
        if "*" in channel:
            prefix, _, suffix = channel.partition("*")
            if not any(n.startswith(prefix) and n.endswith(suffix) for n in channels.names):
                raise SpecError(source, key, "matches no channel of the head", channel)
        else:
            _known(channels, channel, key, source)
        pairs.append((address, channel))
    prefix = t.control_prefix.rstrip("/")
    if not prefix.startswith("/"):
        raise SpecError(source, "inputs.osc.control_prefix", "an OSC address starts with '/'", t.control_prefix)
    for ip in t.control_allow:
        try:
            ipaddress.ip_address(ip)
        except ValueError:
            raise SpecError(source, "inputs.osc.control_allow", "must list IP addresses", ip) from None
    return OscConfig(host, port, tcp, tuple(pairs), prefix, tuple(t.control_allow), t.watchdog)


def _known(channels: ChannelMap, channel: str, key: str, source: str) -> None:
    try:
        channels.index_of(channel)
    except UnknownChannel:
        raise SpecError(source, key, "unknown channel", channel) from None


def _sacn(t: S.SacnTable, head: HeadSpec, channels: ChannelMap, source: str) -> SacnConfig:
    check_host(t.bind, "inputs.sacn.bind", source, t.allow_remote)
    if not 0 <= t.port <= 65535:
        raise SpecError(source, "inputs.sacn.port", "must lie in [0, 65535]", t.port)
    if not 1 <= t.universe <= 63999:
        raise SpecError(source, "inputs.sacn.universe", "must lie in [1, 63999] (E1.31)", t.universe)
    if not 1 <= t.start <= DMX_SLOTS:
        raise SpecError(source, "inputs.sacn.start", f"must lie in [1, {DMX_SLOTS}]", t.start)
    if t.merge not in ("htp", "ltp"):
        raise SpecError(source, "inputs.sacn.merge", "must be 'htp' or 'ltp'", t.merge)
    if not 0 < t.source_timeout_s <= 60:
        raise SpecError(source, "inputs.sacn.source_timeout_s", "must lie in (0, 60] s", t.source_timeout_s)
    if not t.slots:
        raise SpecError(source, "inputs.sacn.slots", "must map at least one channel")
    slots: list[SlotMap] = []
    used: dict[int, str] = {}
    rel = 1
    for i, raw in enumerate(t.slots):
        key = f"inputs.sacn.slots[{i}]"
        s = msgspec.convert(raw, S.SacnSlotTable, strict=True)
        _known(channels, s.channel, f"{key}.channel", source)
        if s.bits not in (8, 16):
            raise SpecError(source, f"{key}.bits", "must be 8 or 16", s.bits)
        rel = rel if s.slot is None else s.slot
        index = t.start - 1 + rel - 1
        width = s.bits // 8
        if rel < 1 or index + width > DMX_SLOTS:
            raise SpecError(source, f"{key}.slot", f"lies outside the universe (start {t.start}, {DMX_SLOTS} slots)",
                            rel)
        for k in range(index, index + width):
            if k in used:
                raise SpecError(source, f"{key}.slot", f"DMX slot {k + 1} is already {used[k]}'s", rel)
            used[k] = s.channel
        lo, hi = _range(s, head, channels, f"{key}.range", source)
        slots.append(SlotMap(s.channel, index, s.bits, lo, hi))
        rel += width
    return SacnConfig(t.bind, t.port, t.universe, tuple(slots), t.merge, float(t.source_timeout_s), t.multicast)


def _range(s: S.SacnSlotTable, head: HeadSpec, channels: ChannelMap, key: str, source: str) -> tuple[float, float]:
    if s.range is not None:
        if len(s.range) != 2 or not all(math.isfinite(v) for v in s.range) or s.range[0] == s.range[1]:
            raise SpecError(source, key, "must be [value at DMX 0, value at full], two different numbers", s.range)
        return float(s.range[0]), float(s.range[1])
    kind = channels.kind(s.channel)
    if kind == "target":
        return 0.0, 1.0
    name = s.channel if kind == "actuator" else next(g.actuators[0] for g in head.groups if g.name == s.channel)
    a = head.actuator(name)
    return a.min / a.unit_scale, a.max / a.unit_scale


_TC = re.compile(r"^(\d{1,2})[:;.](\d{2})[:;.](\d{2})[:;.](\d{2})$")


def timecode_seconds(text: str, rate: str) -> float:
    """``"hh:mm:ss:ff"`` (``;ff`` or not for 29.97 drop frame) at ``rate`` → seconds (ValueError if malformed)."""
    from timecode import Timecode

    m = _TC.match(text.strip())
    if m is None:
        raise ValueError(f"{text!r} is not hh:mm:ss:ff")
    hh, mm, ss, ff = (int(g) for g in m.groups())
    if mm > 59 or ss > 59 or ff >= round(RATES[rate]):
        raise ValueError(f"{text!r} is out of range at {rate} fps")
    sep = ";" if rate == "29.97" else ":"
    frames = Timecode(rate, f"{hh:02d}:{mm:02d}:{ss:02d}{sep}{ff:02d}").frame_number
    return frames / RATES[rate]


def _timecode(t: S.TimecodeTable, source: str) -> TimecodeConfig:
    if t.rate not in RATES:
        raise SpecError(source, "inputs.timecode.rate", f"must be one of {', '.join(RATES)}", t.rate)
    if (t.bind is None) == (t.midi_port is None):
        raise SpecError(source, "inputs.timecode.bind", "give either bind (a TCP MIDI port) or midi_port",
                        t.bind)
    bind = None if t.bind is None else parse_hostport(t.bind, "inputs.timecode.bind", source, t.allow_remote)
    clips: list[tuple[str, float]] = []
    for name, value in t.clips.items():
        key = f"inputs.timecode.clips.{name}"
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise SpecError(source, key, "must be a timecode \"hh:mm:ss:ff\" or seconds", value)
        if isinstance(value, str):
            try:
                offset = timecode_seconds(value, t.rate)
            except ValueError as exc:
                raise SpecError(source, key, str(exc), value) from None
        else:
            offset = float(value)
        if not math.isfinite(offset) or offset < 0:
            raise SpecError(source, key, "must be a finite, non-negative offset", value)
        clips.append((name, offset))
    for key, value, lo, hi in (("freewheel_s", t.freewheel_s, 0.0, 3600.0), ("dropout_s", t.dropout_s, 0.01, 5.0),
                               ("jump_s", t.jump_s, 0.01, 3600.0)):
        if not lo <= value <= hi:
            raise SpecError(source, f"inputs.timecode.{key}", f"must lie in [{lo:g}, {hi:g}] s", value)
    if not 1 <= t.lock_samples <= 100:
        raise SpecError(source, "inputs.timecode.lock_samples", "must lie in [1, 100]", t.lock_samples)
    chase = ChaseParams(tuple(clips), float(t.freewheel_s), float(t.dropout_s), float(t.jump_s), t.lock_samples,
                        "midi_port" if t.bind is None else "mtc")
    return TimecodeConfig(bind, t.midi_port, t.rate, chase)
