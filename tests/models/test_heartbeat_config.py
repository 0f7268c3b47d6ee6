"""``[buses.NAME.heartbeat]``: a typed table naming the drives' producer period and the driver's consumer timeout
(default two periods), handed to the driver as its heartbeat options."""

from __future__ import annotations

from pathlib import Path

import pytest

from models.errors import SpecError
from models.headspec import HEARTBEAT_TIMEOUT_PERIODS, load_head

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"
TABLE = "[buses.can0.heartbeat]\nperiod_s = 0.25    # the drives' producer time (0x1017), written by the driver\n" \
        "timeout_s = 1.0"


def _with(tmp_path: Path, table: str, options_extra: str = "") -> Path:
    text = SAMPLE.read_text()
    start = text.index("[buses.can0.heartbeat]")
    end = text.index("\n[", start + 1)
    text = text[:start] + table + "\n" + text[end:]
    if options_extra:
        text = text.replace("feedback_timeout_s = 1.0", f"feedback_timeout_s = 1.0\n{options_extra}", 1)
    path = tmp_path / "head.toml"
    path.write_text(text)
    return path


def test_the_timeout_defaults_to_two_periods_and_reaches_the_driver_options(tmp_path: Path) -> None:
    head = load_head(_with(tmp_path, "[buses.can0.heartbeat]\nperiod_s = 0.1"))
    hb = head.buses["can0"].heartbeat
    assert HEARTBEAT_TIMEOUT_PERIODS == 2 and (hb.period_s, hb.timeout_s) == (0.1, 0.2)
    opts = head.buses["can0"].driver_options()
    assert (opts["heartbeat_period_s"], opts["heartbeat_timeout_s"]) == (0.1, 0.2)
    assert head.buses["dxl"].heartbeat is None and "heartbeat_period_s" not in head.buses["dxl"].driver_options()
    sample = load_head(SAMPLE).buses["can0"].heartbeat
    assert (sample.period_s, sample.timeout_s) == (0.25, 1.0)


@pytest.mark.parametrize(("table", "extra", "key", "what"), [
    ("[buses.can0.heartbeat]\nperiod_s = 0.1\ntimeout_s = 0.05", "", "buses.can0.heartbeat.timeout_s", "longer"),
    ("[buses.can0.heartbeat]\nperiod_s = 0", "", "buses.can0.heartbeat.period_s", "positive"),
    ("[buses.can0.heartbeat]\nperiod_s = 0.1\nperiod = 1", "", "buses.can0.heartbeat.period", "unknown key"),
    ("[buses.can0.heartbeat]\ntimeout_s = 0.2", "", "buses.can0.heartbeat.period_s", "missing"),
    ("[buses.can0.heartbeat]\nperiod_s = \"fast\"", "", "buses.can0.heartbeat.period_s", "float"),
    (TABLE, "heartbeat_timeout_s = 0.3", "buses.can0.options.heartbeat_timeout_s", "only"),
])
def test_a_bad_heartbeat_table_is_named(tmp_path: Path, table: str, extra: str, key: str, what: str) -> None:
    with pytest.raises(SpecError) as info:
        load_head(_with(tmp_path, table, extra))
    text = str(info.value)
    assert key in text and what in text and "\n" not in text, text
