"""Daemon settings from the head spec: defaults, overrides, errors naming file, key and value; the solve stage."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from models.errors import SpecError
from models.headspec import load_head
from runtime.config import daemon_config, endpoint_problem
from runtime.solve import SolveResult, TargetSolver

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"
HEAD = load_head(SAMPLE)


def test_sample_settings_and_overrides() -> None:
    cfg = daemon_config(HEAD)
    assert cfg.runtime.rate_hz == 250 and cfg.api.command == "tcp://127.0.0.1:5555"
    cfg = daemon_config(HEAD, {"runtime.rate_hz": 1000, "api.command": "tcp://127.0.0.1:*"})
    assert cfg.runtime.rate_hz == 1000.0


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        ({"runtime.rate_hz": 5000}, "runtime.rate_hz"),
        ({"runtime.rate_hz": "fast"}, "runtime.rate_hz"),
        ({"runtime.bogus": 1}, "runtime.bogus"),
        ({"safety.fault_action": "explode"}, "safety.fault_action"),
        ({"api.command": "tcp://0.0.0.0:5555"}, "api.command"),
        ({"api.curve_secret_key": "nope.key_secret"}, "api.curve_allow_dir"),
        ({"safety.watchdog_neutral_s": 0.1}, "safety.watchdog_neutral_s"),
        ({"runtime.stream_phase_lead_s": 0.0}, "runtime.stream_phase_lead_s"),
        ({"runtime.api_priority": 99}, "runtime.api_priority"),
        ({"runtime.stream_phase_lock": True, "runtime.stream_phase_lead_s": 0.003}, "runtime.stream_phase_lead_s"),
    ],
)
def test_bad_settings_name_file_key_and_value(overrides: dict, key: str) -> None:
    with pytest.raises(SpecError) as info:
        daemon_config(HEAD, overrides)
    assert key in str(info.value)
    assert str(SAMPLE) in str(info.value) or "<overrides>" in str(info.value)


def test_endpoint_rules() -> None:
    assert endpoint_problem("tcp://127.0.0.1:*", False) is None
    assert endpoint_problem("tcp://localhost:5555", False) is None
    assert "loopback" in endpoint_problem("tcp://10.0.0.1:5555", False)
    assert endpoint_problem("tcp://10.0.0.1:5555", True) is None
    assert endpoint_problem("udp://127.0.0.1:1", False) is not None


class _Weights:
    """A toy target solver: 'expr.open' opens the jaw proportionally (stands in for a skin predictor)."""

    def channels(self) -> dict[str, str]:
        return {"expr.open": "weight"}

    def handles(self, channel: str) -> bool:
        return channel.startswith("expr.")

    def solve(self, targets, current) -> SolveResult:
        return SolveResult({"jaw": math.radians(20) * targets["expr.open"]}, {"residual": 0.0})


def test_solve_stage_units_groups_and_target_channels() -> None:
    import numpy as np

    from runtime.config import daemon_config
    from runtime.core import core as K
    from runtime.core.channels import ChannelMap, UnknownChannel
    from runtime.core.cycle import CycleOutputs
    from runtime.core.params import CoreParams
    from runtime.core.solvers import as_array_solvers, channel_sets
    from runtime.core.state import CoreState

    solvers = [_Weights()]
    assert isinstance(solvers[0], TargetSolver)
    cm = ChannelMap.build(HEAD, channel_sets(solvers))
    assert cm.kind("blink") == "group" and cm.kind("expr.open") == "target" and cm.kind("jaw") == "actuator"
    params = CoreParams.build(HEAD, daemon_config(HEAD), cm, [(b, [a.name for a in HEAD.actuators_on(b)])
                                                               for b in HEAD.buses])
    state = CoreState.initial(HEAD, params, as_array_solvers(solvers, cm.target_blocks, cm.names,
                                                               HEAD.actuator_names))
    out = CycleOutputs()

    def solve(**values: float) -> dict[str, float]:
        vec = np.full(cm.n, np.nan)
        for ch, v in values.items():
            vec[cm.index_of(ch.replace("__", "."))] = v
        x = K.solve_channels(state, params, out, vec)
        return {n: v for n, v in zip(HEAD.actuator_names, x.tolist(), strict=True) if v == v}

    res = solve(blink=30.0, brow_l=10.0, expr__open=0.5)
    assert res["lid_l"] == pytest.approx(math.radians(30)) == res["lid_r"]
    assert res["brow_l"] == pytest.approx(math.radians(10))
    assert res["jaw"] == pytest.approx(math.radians(10)) and state.solve.extra == {"residual": 0.0}
    assert solve(jaw=5.0, expr__open=1.0)["jaw"] == pytest.approx(math.radians(5))
    with pytest.raises(UnknownChannel):
        cm.indices(["jaw", "arkit.jawOpen"])
