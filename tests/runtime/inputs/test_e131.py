"""The sACN input's packet reader reads what the ``sacn`` library's parser reads, and refuses what it refuses."""

from __future__ import annotations

import pytest
from sacn.messages.data_packet import DataPacket

from runtime.inputs import e131

FIELDS = ("sourceName", "universe", "priority", "sequence", "option_PreviewData", "option_StreamTerminated",
          "dmxStartCode")


def _raw(**kw: object) -> bytes:
    args: dict = {"cid": tuple(range(16)), "sourceName": "console ü", "universe": 7, "dmxData": tuple(range(200)),
                  "priority": 150, "sequence": 9}
    args.update(kw)
    return bytes(DataPacket(**args).getBytes())


@pytest.mark.parametrize("kw", [{}, {"previewData": True}, {"streamTerminated": True}, {"universe": 63999},
                                {"dmxData": ()}, {"dmxData": tuple([255] * 512)}, {"priority": 0}])
def test_reads_the_fields_the_library_reads(kw: dict) -> None:
    raw = _raw(**kw)
    ref, got = DataPacket.make_data_packet(raw), e131.parse(raw)
    for field in FIELDS:
        assert getattr(got, field) == getattr(ref, field), field
    assert got.cid == bytes(ref.cid)
    assert tuple(got.dmxData.tolist()) == tuple(ref.dmxData)[:len(got.dmxData)]
    assert not any(tuple(ref.dmxData)[len(got.dmxData):])  # the library pads with zeros: the same values


def test_refuses_what_is_not_e131_data() -> None:
    raw = bytearray(_raw())
    with pytest.raises(TypeError):
        e131.parse(bytes(raw[:100]))
    bad = bytearray(raw)
    bad[21] = 8  # root vector
    with pytest.raises(TypeError):
        e131.parse(bytes(bad))
    bad = bytearray(raw)
    bad[117] = 0  # DMP vector
    with pytest.raises(TypeError):
        e131.parse(bytes(bad))


def test_refuses_fields_out_of_range() -> None:
    raw = bytearray(_raw())
    raw[108] = 201  # priority
    with pytest.raises(ValueError, match="priority"):
        e131.parse(bytes(raw))
    raw = bytearray(_raw())
    raw[113], raw[114] = 0, 0  # universe 0
    with pytest.raises(ValueError, match="universe"):
        e131.parse(bytes(raw))
    raw = bytearray(_raw())
    raw[44] = 0xFF  # not UTF-8
    with pytest.raises(ValueError, match="UTF-8"):
        e131.parse(bytes(raw))
