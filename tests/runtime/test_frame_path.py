"""A stream frame's path, read from signatures alone: each stop's annotations name the types the next stop takes.

socket → ``Server._request`` → ``decode_request`` (a ``Request``) → ``to_command`` (a core ``Command``) → the command
pipe (``PipeWriter[ToLoop]`` → ``PipeReader[Command]``) → ``Runner._drain`` → ``CycleInputs.commands`` →
``step`` → ``CycleOutputs.write`` → ``BusProxy.post`` (the bus process) → ``MotorBus.write``; and back:
``Runner._send`` (``FromLoop``) → ``recv_from_loop`` → ``Server._core_reply``. Large requests take the decoder
process (``DecodeJob`` → ``Decoded``), show-control inputs the hub (``InputHub.drain``). Nothing on the way is
``Any``.
"""

from __future__ import annotations

import typing
from collections.abc import Callable, Sequence
from typing import Any, get_args, get_type_hints

import numpy as np

from drivers.base import MotorBus
from runtime import decoder as D
from runtime import ipc
from runtime import loop_messages as L
from runtime import messages as M
from runtime import requests as R
from runtime import server as S
from runtime.bus import BusProxy
from runtime.core import commands as C
from runtime.core import core as K
from runtime.core.cycle import CycleInputs, CycleOutputs
from runtime.core.events import Body
from runtime.inputs.hub import InputHub
from runtime.runner import Runner


def _hints(obj: Callable[..., object] | type) -> dict[str, object]:
    return get_type_hints(obj)


def _mentions_any(hint: object) -> bool:
    if hint is Any:
        return True
    return any(_mentions_any(arg) for arg in get_args(hint))


def test_the_server_decodes_a_request_and_sends_the_core_command_down_the_pipe() -> None:
    assert _hints(S.Server._request) == {"frames": list[bytes], "received": float, "return": type(None)}
    assert _hints(M.decode_request) == {"raw": bytes, "return": M.Request}
    to_command = _hints(R.to_command)
    assert to_command["req"] == M.Request and to_command["return"] == C.Command
    assert _hints(S.Server._to_core)["cmd"] == L.ToLoop == C.Command
    assert _hints(S.Server)["to_loop"] == ipc.PipeWriter[L.ToLoop]
    # every request the core serves is named after its command: EStopRequest → EStop, StopMotionRequest → StopMotion
    local = set(get_args(R.LocalRequest))
    for req in set(get_args(M.Request)) - local:
        command = req.__name__.removesuffix("Request")
        assert isinstance(getattr(C, command, None), type), req.__name__


def test_large_requests_take_the_decoder_process_to_the_same_command() -> None:
    assert _hints(D.DecoderProcess.submit)["job"] is D.DecodeJob
    decode = _hints(D.decode)
    assert decode["job"] is D.DecodeJob and decode["return"] is D.Decoded
    assert _hints(D.Decoded)["command"] == C.Command | None
    assert _hints(D.DecoderProcess.drain)["return"] == list[D.Decoded]


def test_the_pipe_carries_commands_and_the_runner_hands_them_to_the_core() -> None:
    assert _hints(ipc.PipeWriter.send)["obj"] is _hints(ipc.PipeReader.recv)["return"].__args__[0]  # the same T
    runner = _hints(Runner.__init__)
    assert runner["commands"] == ipc.PipeReader[C.Command]
    assert _hints(Runner._drain)["return"] == list[C.Command]
    assert _hints(Runner._inputs)["return"] is CycleInputs
    assert _hints(CycleInputs)["commands"] == tuple[C.Command, ...]
    step = _hints(K.step)
    assert step["inputs"] is CycleInputs and step["return"] is CycleOutputs


def test_the_core_output_reaches_the_bus_and_the_driver() -> None:
    assert _hints(Runner._write)["out"] is CycleOutputs
    assert _hints(CycleOutputs)["write"] == np.ndarray | None
    assert _hints(Runner.__init__)["buses"] == Sequence[BusProxy]
    post = _hints(BusProxy.post)
    assert post["targets"] is np.ndarray
    write = _hints(MotorBus.write)
    assert "targets" in write and write["return"] is type(None)


def test_what_the_loop_sends_back_is_one_typed_union_the_server_matches_on() -> None:
    members = set(get_args(L.FromLoop))
    assert members == {L.Reply, L.Event, L.StateSnapshot, L.LoopStatistics, L.RecordedRows, L.RealtimeStatus,
                       L.StopServer}
    assert _hints(Runner._send)["msg"] == L.FromLoop
    assert _hints(L.send_to_server)["msg"] == L.FromLoop
    assert _hints(L.recv_from_loop)["return"] == L.FromLoop
    assert _hints(L.Reply) == {"token": int, "body": Body}
    reply = _hints(S.Server._core_reply)
    assert reply["token"] is int and reply["body"] == Body


def test_show_control_inputs_hand_the_server_core_commands() -> None:
    assert _hints(InputHub.drain)["return"] == list[C.Command]
    assert _hints(InputHub.emit)["cmd"] == C.Command


def test_no_stop_on_the_path_is_typed_any() -> None:
    stops: list[Callable[..., object] | type] = [
        S.Server._request, S.Server._to_core, S.Server._core_reply, S.Server._drain_loop, S.Server,
        M.decode_request, R.to_command, D.decode, D.Decoded, D.DecodeJob, ipc.PipeWriter.send, ipc.PipeReader.recv,
        Runner.__init__, Runner._drain, Runner._inputs, Runner._write, Runner._send, L.send_to_server,
        L.recv_from_loop, *get_args(L.FromLoop), InputHub.drain,
    ]
    for stop in stops:
        for name, hint in _hints(stop).items():
            assert not _mentions_any(hint), f"{getattr(stop, '__qualname__', stop)}: {name} is {hint}"
    assert typing.get_origin(L.FromLoop) is not None  # a union, matched by the server
