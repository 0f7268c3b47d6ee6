"""Typed errors end to end: the runtime raises kinds of :mod:`models.errors`; one table maps them to protocol codes
(every documented code kept), one table maps them to the exit status of ``likeness`` commands."""

from __future__ import annotations

import inspect
import re
import socket
from pathlib import Path

import pytest

from drivers.errors import BusInitError
from drivers.errors import ConfigError as DriverConfigError
from likeness.cli import exit_status, main
from models import errors as E
from models import protocol as P
from models.client import DaemonError, DaemonTimeout
from models.errors import SpecError
from runtime.core import commands as C
from runtime.daemon import DaemonStartError
from tests.runtime.test_core import Rig

ROOT = Path(__file__).resolve().parents[2]


def test_every_documented_code_has_exactly_one_kind() -> None:
    text = (ROOT / "docs" / "protocol.md").read_text()
    paragraph = text[text.index("Error codes:"):text.index("`internal`", text.index("Error codes:")) + 10]
    documented = set(re.findall(r"`([a-z_]+)`", paragraph)) - {"reset"}  # codes, and the op they point to
    assert documented == set(P.ERROR_CODES), documented ^ set(P.ERROR_CODES)
    assert sorted(P.ERROR_CODE_OF.values()) == sorted(P.ERROR_CODES)  # one kind per code, none left out
    for code in P.ERROR_CODES:
        err = P.error_for(code, "why")
        assert isinstance(err, E.LikenessError) and P.code_of(err) == code and err.message == "why"


def test_kinds_map_through_their_nearest_listed_base() -> None:
    class ClipTooLong(E.BadValue):
        pass

    assert P.code_of(ClipTooLong("x")) == "bad_value"
    assert P.code_of(E.UnknownChannel("x")) == "unknown_channel"
    assert P.code_of(E.Faulted("x")) == "fault" and isinstance(E.Faulted("x"), E.BadState)
    assert P.code_of(ZeroDivisionError()) == "internal"
    assert P.error_body(KeyError("k")) == {"code": "internal", "message": "KeyError: 'k'"}
    kinds = [c for _, c in inspect.getmembers(E, inspect.isclass) if issubclass(c, E.LikenessError)]
    assert all(P.code_of(k("file", "key", "x") if issubclass(k, E.SpecError) else k("x")) in P.ERROR_CODES
               for k in kinds)


def test_the_core_answers_refusals_with_the_code_of_their_kind() -> None:
    rig = Rig()
    assert rig.call(C.Play, name="probe")["error"]["code"] == "bad_state"  # inactive
    assert rig.call(C.Enable)["lifecycle"] == "active"
    assert rig.call(C.Play, name="nope")["error"] == {
        "code": "not_found", "message": "no clip 'nope' loaded; loaded: []"}
    assert rig.call(C.EStop, reason="test")["lifecycle"] == "estop"
    assert rig.call(C.Enable)["error"]["code"] == "estop"


@pytest.mark.parametrize(("exc", "status"), [
    (SpecError("head.toml", "saftey", "unknown table"), 2),
    (DriverConfigError("buses.dxl.options.port", "missing"), 2),
    (E.ConfigError("x"), 2),
    (E.UnknownChannel("x"), 2),
    (DaemonError("play", "not_found", "no clip"), 2),
    (BusInitError("bus 'can0': no server"), 3),
    (DaemonStartError("the API server process did not start"), 3),
    (DaemonError("enable", "hardware", "bus can0 is not connected"), 3),
    (DaemonTimeout("no reply"), 4),
    (DaemonError("enable", "fault", "send reset"), 5),
    (DaemonError("pose", "estop", "send reset"), 5),
    (E.InternalError("bug"), 70),
])
def test_one_table_maps_every_kind_to_an_exit_status(exc: BaseException, status: int) -> None:
    assert exit_status(exc.error if isinstance(exc, DaemonError) else exc) == status
    assert exit_status(exc) == status


def test_a_command_that_reaches_no_daemon_exits_4_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(["status", "--endpoint", f"tcp://127.0.0.1:{port}", "--timeout", "0.2"]) == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("likeness status: error: ")


def test_a_config_error_stops_the_daemon_at_start_up_with_status_2(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    head = tmp_path / "head.toml"
    text = (ROOT / "heads" / "sample" / "head.toml").read_text()
    head.write_text(text.replace("[buses.can0.heartbeat]\nperiod_s = 0.25", "[buses.can0.heartbeat]\nperiod_s = -1"))
    assert main(["daemon", "--config", str(head)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "buses.can0.heartbeat.period_s" in err[0] and "positive" in err[0], err
