"""The pure parts of the show-control inputs, stepped without sockets: the OSC address map, DMX slot decoding and
the merge of sACN sources, MTC assembly, the chase state machine, live values, and the [inputs] config."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.errors import SpecError
from models.headspec import head_from_dict, load_head
from runtime.core.channels import ChannelMap
from runtime.core.chase import Chase, ChaseParams
from runtime.core.live import LiveValues
from runtime.inputs.config import RATES, SlotMap, inputs_config, timecode_seconds
from runtime.inputs.dmx import Merger, SlotDecoder
from runtime.inputs.mtc import MtcAssembler, MtcError, frame_of, full_frame, quarter_frames
from runtime.inputs.oscmap import OscMap

SAMPLE = Path(__file__).resolve().parents[3] / "heads" / "sample" / "head.toml"
HEAD = load_head(SAMPLE)
CHANNELS = ChannelMap.build(HEAD, [{"arkit.jawOpen": "weight", "arkit.browInnerUp": "weight"}])


# ---------------------------------------------------------------------- OSC address map
def test_osc_map_resolves_addresses_wildcards_and_patterns() -> None:
    m = OscMap([("/face/jaw", "jaw"), ("/face/brow/*", "brow_*"), ("/face/arkit/*", "arkit.*")], CHANNELS,
               "/likeness")
    idx = CHANNELS.index_of
    assert m.resolve("/face/jaw") == ([idx("jaw")], None)
    assert m.resolve("/face/brow/l") == ([idx("brow_l")], None)
    assert m.resolve("/face/arkit/jawOpen") == ([idx("arkit.jawOpen")], None)
    assert sorted(m.resolve("/face/brow/{l,r}")[0]) == sorted([idx("brow_l"), idx("brow_r")])  # incoming pattern
    assert m.resolve("/likeness/estop") == ([], "estop")
    assert m.resolve("/face/nose") == ([], None)
    assert m.resolve("/face/arkit/nope") == ([], None)  # names no channel of the head
    assert sorted(m.resolve("/face/arkit/*")[0]) == sorted([idx("arkit.browInnerUp"), idx("arkit.jawOpen")])


# ---------------------------------------------------------------------- DMX
def test_slot_decoder_8_and_16_bit() -> None:
    dec = SlotDecoder([SlotMap("jaw", 0, 8, -2.0, 28.0), SlotMap("brow_l", 1, 16, 0.0, 100.0),
                       SlotMap("blink", 3, 8, 40.0, 0.0)])
    dmx = np.zeros(512, dtype=np.uint8)
    assert dec.decode(dmx).tolist() == [-2.0, 0.0, 40.0]
    dmx[0], dmx[1], dmx[2], dmx[3] = 255, 0x80, 0x00, 51
    v = dec.decode(dmx)
    assert v[0] == 28.0
    assert v[1] == pytest.approx(100.0 * 0x8000 / 65535)  # coarse then fine
    assert v[2] == pytest.approx(40.0 - 40.0 * 51 / 255)  # a reversed range
    dmx[2] = 0xFF
    assert dec.decode(dmx)[1] == pytest.approx(100.0 * 0x80FF / 65535)


def _u(**slots: int) -> list[int]:
    data = [0] * 512
    for k, v in slots.items():
        data[int(k[1:])] = v
    return data


def test_merge_highest_priority_then_htp_or_ltp_and_source_timeout() -> None:
    m = Merger("htp", timeout=2.5)
    assert m.merged() is None
    assert m.update(b"A", 100, _u(s0=10, s1=200), 0.0, "console") == (True, True)
    assert m.update(b"B", 100, _u(s0=50, s1=20), 0.1, "backup") == (True, True)
    out = m.merged()
    assert out is not None and out[0] == 50 and out[1] == 200  # HTP: the highest per slot
    m.update(b"C", 150, _u(s0=5), 0.2, "override")
    assert m.merged()[0] == 5 and m.merged()[1] == 0  # only the highest priority counts
    m.update(b"B", 100, _u(s0=50, s1=20), 2.6, "backup")  # B keeps sending, A falls silent
    assert m.expire(2.65) == ["console"]  # A was silent for 2.65 s
    assert m.expire(2.71) == ["override"]
    assert m.merged()[0] == 50  # back to the lower priority source still sending
    ltp = Merger("ltp")
    ltp.update(b"A", 100, _u(s0=10, s1=200), 0.0)
    ltp.update(b"B", 100, _u(s0=50, s1=20), 0.1)
    assert ltp.merged()[:2].tolist() == [50, 20]  # B changed both last
    ltp.update(b"A", 100, _u(s0=30, s1=200), 0.2)  # A changes slot 0 only
    assert ltp.merged()[:2].tolist() == [30, 20]


def test_merge_drops_packets_out_of_sequence() -> None:
    m = Merger()
    assert m.update(b"A", 100, _u(s0=1), 0.0, sequence=10)[0]
    assert not m.update(b"A", 100, _u(s0=2), 0.1, sequence=9)[0]  # behind: dropped
    assert m.update(b"A", 100, _u(s0=3), 0.2, sequence=11)[0]
    assert m.update(b"A", 100, _u(s0=4), 0.3, sequence=200)[0]  # far jump: a restarted source
    assert m.merged()[0] == 4


# ---------------------------------------------------------------------- MTC
@pytest.mark.parametrize("rate", ["24", "25", "29.97", "30"])
def test_mtc_quarter_and_full_frames_round_trip(rate: str) -> None:
    a = MtcAssembler()
    seconds = 3725.5  # 01:02:05.5
    frame = frame_of(seconds, rate)
    samples = [a.feed(m, 7.0) for m in quarter_frames(frame, rate)]
    assert samples[:7] == [None] * 7
    s = samples[7]
    assert s is not None and not s.full and s.received == 7.0
    fps = RATES[rate]
    assert s.fps == pytest.approx(fps)
    assert s.seconds == pytest.approx((frame + 1.75) / fps)  # as of piece 7: the encoded frame + 7/4 frames
    assert abs(s.seconds - 1.75 / fps - seconds) < 1.0 / fps
    f = a.feed(full_frame(frame, rate), 8.0)
    assert f is not None and f.full and f.seconds == pytest.approx(frame / fps)
    assert s.rate == ("29.97df" if rate == "29.97" else rate)


def test_mtc_drop_frame_labels_and_bad_messages() -> None:
    import mido

    a = MtcAssembler()
    # 29.97 drop frame: frame numbers 00:00:59;29 → 00:01:00;02 (frames 00 and 01 are dropped at the minute)
    last = None
    for msg in quarter_frames(1799, "29.97"):
        last = a.feed(msg, 0.0)
    assert last is not None and last.label == "00:00:59;29"
    for msg in quarter_frames(1800, "29.97"):
        last = a.feed(msg, 0.0)
    assert last is not None and last.label == "00:01:00;02"
    assert timecode_seconds("00:01:00;02", "29.97") == pytest.approx(1800 / RATES["29.97"])
    # a sequence missing a piece gives nothing; a message that is no timecode is an error
    qf = quarter_frames(100, "25")
    assert [a.feed(m, 0.0) for m in qf[:3] + qf[4:]] == [None] * 7
    with pytest.raises(MtcError):
        a.feed(mido.Message("note_on", note=60), 0.0)
    with pytest.raises(MtcError, match="does not exist"):
        a.feed(mido.Message("sysex", data=[0x7F, 0x7F, 1, 1, 2 << 5, 1, 0, 0]), 0.0)


# ---------------------------------------------------------------------- chase
def _run(chase: Chase, tc0: float, t0: float, t1: float, step: float = 0.08) -> None:
    """Samples of running timecode from t0 to t1 (daemon time), timecode tc0 at t0."""
    t = t0
    while t < t1 - 1e-9:
        chase.feed(tc0 + (t - t0), t, 25.0, "25", "")
        chase.update(t)
        t += step


def test_chase_locks_freewheels_holds_and_relocks() -> None:
    c = Chase(ChaseParams(clips=(("a", 10.0), ("b", 20.0)), freewheel_s=1.0, dropout_s=0.15, jump_s=0.25,
                          lock_samples=3))
    assert c.state == "stopped" and c.position(0.0) is None
    assert c.feed(12.0, 0.0, 25.0, "25", "") == ""
    assert c.state == "locking" and c.position(0.0) is None
    c.feed(12.08, 0.08, 25.0, "25", "")
    assert c.feed(12.16, 0.16, 25.0, "25", "") == "lock"
    assert c.state == "locked" and c.position(0.2) == pytest.approx(12.2)
    assert c.clip_at(12.2) == ("a", pytest.approx(2.2))
    # dropout: freewheel at speed 1 for 1 s after the last sample, then hold there
    assert c.update(0.35) == "freewheel"
    assert c.position(0.9) == pytest.approx(12.9)
    assert c.update(1.1) == ""
    assert c.update(1.2) == "hold"
    assert c.position(1.5) == pytest.approx(13.16) and c.position(3.0) == pytest.approx(13.16)
    # timecode comes back elsewhere: it holds until locked again, then follows
    _run(c, 25.0, 3.0, 3.2)
    assert c.state == "locked" and c.position(3.2) == pytest.approx(25.2)
    assert c.clip_at(25.2) == ("b", pytest.approx(5.2))


def test_chase_jumps_relocate_and_full_frame_parks() -> None:
    c = Chase(ChaseParams(jump_s=0.25, lock_samples=2))
    _run(c, 100.0, 0.0, 0.4)
    assert c.state == "locked"
    assert c.feed(50.0, 0.4, 25.0, "25", "") == "jump"  # way off the running position
    assert c.state == "locked" and c.position(0.5) == pytest.approx(50.1) and c.jumps == 1
    assert c.feed(50.12, 0.52, 25.0, "25", "") == ""  # small differences only re-anchor
    assert c.feed(70.0, 0.6, 25.0, "25", "", full=True) == "jump"  # a locate parks
    assert c.state == "hold" and c.position(5.0) == pytest.approx(70.0)
    assert c.clip_at(70.0) is None  # no clips configured


# ---------------------------------------------------------------------- live values
def test_live_values_hold_per_channel_and_apply_timed_updates_whole() -> None:
    lv = LiveValues(4)
    out = np.empty(4)
    assert not lv.evaluate(0.0, out)
    lv.push(0.0, np.array([0]), np.array([1.0]))
    lv.push(0.1, np.array([1, 2]), np.array([2.0, 3.0]), at=0.5)  # a bundle with a timetag
    assert lv.evaluate(0.2, out) and out[0] == 1.0 and np.isnan(out[1:]).all()
    lv.push(0.3, np.array([0]), np.array([5.0]))  # other channels keep their values
    lv.evaluate(0.5, out)
    assert out[:3].tolist() == [5.0, 2.0, 3.0] and np.isnan(out[3])
    assert lv.starved_for(1.0) == pytest.approx(0.7)


# ---------------------------------------------------------------------- config
def _head(inputs: dict) -> object:
    import tomllib

    data = tomllib.loads(SAMPLE.read_text())
    data["inputs"] = inputs
    return head_from_dict(data, SAMPLE)


def test_inputs_config_validates_against_the_head() -> None:
    cfg = inputs_config(_head({
        "osc": {"bind": "127.0.0.1:0", "map": {"/face/jaw": "jaw"}, "control_allow": ["127.0.0.1"]},
        "sacn": {"universe": 7, "start": 10, "slots": [{"channel": "jaw", "bits": 16}, {"channel": "blink"}]},
        "timecode": {"bind": "127.0.0.1:0", "rate": "25", "clips": {"show": "01:00:00:00", "tail": 3610.5}},
    }), CHANNELS)
    assert cfg.osc is not None and cfg.osc.map == (("/face/jaw", "jaw"),)
    assert cfg.sacn is not None
    jaw, blink = cfg.sacn.slots
    assert (jaw.index, jaw.bits, jaw.lo, jaw.hi) == (9, 16, -2.0, 28.0)  # the actuator's range by default
    assert blink.index == 11  # after the jaw's two slots
    assert cfg.timecode is not None and cfg.timecode.chase.clips == (("show", 3600.0), ("tail", 3610.5))


@pytest.mark.parametrize(("inputs", "key"), [
    ({"osc": {"bind": "10.1.2.3:9000"}}, "inputs.osc.bind"),  # beyond loopback without allow_remote
    ({"osc": {"map": {"/face/nose": "nose"}}}, "inputs.osc.map"),
    ({"osc": {"bnd": "127.0.0.1:9000"}}, "inputs.osc.bnd"),  # unknown key
    ({"sacn": {"slots": [{"channel": "jaw", "bits": 12}]}}, "inputs.sacn.slots[0].bits"),
    ({"sacn": {"start": 512, "slots": [{"channel": "jaw", "bits": 16}]}}, "inputs.sacn.slots[0].slot"),
    ({"sacn": {"slots": [{"channel": "jaw"}, {"channel": "blink", "slot": 1}]}}, "inputs.sacn.slots[1].slot"),
    ({"sacn": {"merge": "avg", "slots": [{"channel": "jaw"}]}}, "inputs.sacn.merge"),
    ({"timecode": {"rate": "23.976"}}, "inputs.timecode.rate"),
    ({"timecode": {"clips": {"x": "01:00:00:30"}}}, "inputs.timecode.clips.x"),
    ({"timecode": {"bind": "127.0.0.1:0", "midi_port": "MTC"}}, "inputs.timecode.bind"),
])
def test_inputs_config_errors_name_the_key(inputs: dict, key: str) -> None:
    with pytest.raises(SpecError) as err:
        inputs_config(_head(inputs), CHANNELS)
    assert err.value.key.startswith(key), err.value


# ---------------------------------------------------------------------- OSC packets (no sockets)
def test_osc_packets_become_one_command_per_bundle_and_control_needs_the_allow_list() -> None:
    import time

    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message_builder import OscMessageBuilder

    from runtime.core import commands as C
    from runtime.inputs.config import OscConfig
    from runtime.inputs.osc import OscInput

    cfg = OscConfig("127.0.0.1", 0, None, (("/face/jaw", "jaw"), ("/face/brow/*", "brow_*")), "/likeness",
                    ("127.0.0.1",), True)
    got: list[C.Command] = []
    trips: list[str] = []
    osc = OscInput(cfg, CHANNELS, got.append, trips.append)

    def msg(address: str, *args: object) -> object:
        m = OscMessageBuilder(address)
        for a in args:
            m.add_arg(a)
        return m.build()

    def bundle(*msgs: object, timetag: float = IMMEDIATELY) -> bytes:
        b = OscBundleBuilder(timetag)
        for m in msgs:
            b.add_content(m)
        return b.build().dgram

    local, remote = ("127.0.0.1", 5000), ("127.0.0.9", 5000)
    osc.packet(bundle(msg("/face/jaw", 4.0), msg("/face/brow/l", 2.0), msg("/face/brow/r", 2)), local)
    assert len(got) == 1 and isinstance(got[0], C.Live)
    assert sorted(got[0].channels.tolist()) == sorted(CHANNELS.indices(["jaw", "brow_l", "brow_r"]).tolist())
    assert got[0].at is None  # "immediately"
    later = time.time() + 0.5
    osc.packet(bundle(msg("/face/jaw", 1.0), timetag=later), local)
    assert got[1].at is not None and 0.3 < got[1].at - got[1].received < 0.7  # its timetag on the daemon clock
    osc.packet(bundle(msg("/face/jaw", 1.0), msg("/face/nose", 1.0)), local)  # one bad message: all refused
    osc.packet(msg("/face/jaw", "open").dgram, local)
    osc.packet(msg("/face/jaw", float("nan")).dgram, local)
    osc.packet(b"\x00garbage", local)
    assert len(got) == 2
    assert set(osc.refusals.snapshot()) == {"unmapped address", "not one number", "non-finite value",
                                            "malformed OSC"}
    osc.packet(msg("/likeness/estop", "cue 12").dgram, remote)  # not on control_allow
    assert len(got) == 2 and not trips
    osc.packet(msg("/likeness/estop", "cue 12").dgram, local)
    assert trips == ["cue 12"] and isinstance(got[2], C.EStop) and got[2].reason == "cue 12"
    osc.packet(msg("/likeness/play", "hi", 1).dgram, local)
    assert isinstance(got[3], C.Play) and got[3].name == "hi" and got[3].loop and got[3].source == "osc"
