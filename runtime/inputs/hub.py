"""The show-control inputs of one daemon, in the API server process: starts them, collects their commands.

Each input's I/O runs on threads of its own (python-osc's server, the sACN receiver, the timecode port server).
With a ``forward`` callable (the API server's), an input's thread hands each command straight to it, and it goes
on to the command pipe from that thread: a packet then wakes one thread of this process, not two (a thread hand-off
costs 0.5–2 ms on a busy two-core host). Without one, commands queue on an in-process ZeroMQ PUSH socket (under a
lock) for the owner to :meth:`InputHub.drain`; the PULL end also carries the wake-ups :meth:`InputHub.wake_owner`
sends when a forwarded command could not be written whole. Nothing here runs in the control loop's process.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
from collections.abc import Callable, Mapping
from typing import Protocol, cast

import zmq

from runtime import ipc
from runtime.core import commands as C
from runtime.core.channels import ChannelMap
from runtime.inputs.config import InputsConfig
from runtime.inputs.refusals import Refusals
from runtime.rtbudget import RealtimeBudget

_ENDPOINTS = itertools.count(1)


class ShowInput(Protocol):
    """What the hub needs of an input (OSC, sACN, timecode): its name and refusal counter, start and close, where it
    listens (``bound``, for ``hello``) and its counters (``stats``, for ``status``)."""

    name: str
    refusals: Refusals

    @property
    def bound(self) -> Mapping[str, object]: ...

    def start(self) -> None: ...

    def close(self) -> None: ...

    def stats(self) -> Mapping[str, object]: ...


class InputHub:
    """Starts the configured inputs; :attr:`pull` yields their commands (token 0, to be given one)."""

    def __init__(self, cfg: InputsConfig, channels: ChannelMap, ctx: zmq.Context, trip_estop: Callable[[str], None],
                 forward: Callable[[C.Command], bool] | None = None, priority: int | RealtimeBudget = 0) -> None:
        self.cfg = cfg
        self.forward = forward  # on the inputs' threads: True once the command is on its way, False when queued
        endpoint = f"inproc://likeness-inputs-{next(_ENDPOINTS)}"
        self.pull = ctx.socket(zmq.PULL)
        self.pull.setsockopt(zmq.LINGER, 0)
        self.pull.bind(endpoint)
        self._push = ctx.socket(zmq.PUSH)
        self._push.setsockopt(zmq.LINGER, 0)
        self._push.setsockopt(zmq.SNDHWM, 10000)
        self._push.connect(endpoint)
        self._lock = threading.Lock()
        self.refusals: dict[str, Refusals] = {}
        self.inputs: list[ShowInput] = []
        if cfg.osc is not None:
            from runtime.inputs.osc import OscInput

            self.inputs.append(OscInput(cfg.osc, channels, self.emit, trip_estop, priority))
        if cfg.sacn is not None:
            from runtime.inputs.sacn import SacnInput

            self.inputs.append(SacnInput(cfg.sacn, channels, self.emit, priority))
        if cfg.timecode is not None:
            from runtime.inputs.timecode import TimecodeInput

            self.inputs.append(TimecodeInput(cfg.timecode, self.emit, priority))
        for inp in self.inputs:
            self.refusals[inp.name] = inp.refusals

    def start(self) -> None:
        for inp in self.inputs:
            inp.start()

    def emit(self, cmd: C.Command) -> None:
        """Called from the inputs' threads; never blocks (a full queue drops the command, logged)."""
        if self.forward is not None:
            if not self.forward(cmd):
                self.wake_owner()
            return
        with self._lock:
            try:
                ipc.send(self._push, cmd, zmq.NOBLOCK)
            except zmq.Again:
                source = getattr(cmd, "source", "input")
                self.refusals.get(source, Refusals(source)).refuse("queue to the control loop full")

    def wake_owner(self) -> None:
        """Wake the thread that polls :attr:`pull` (a forwarded command waits for it to finish writing it)."""
        with self._lock, contextlib.suppress(zmq.Again):  # wake-ups already queued
            ipc.send(self._push, None, zmq.NOBLOCK)

    def drain(self, limit: int = 256) -> list[C.Command]:
        """The commands waiting (server thread); wake-ups are taken and left out."""
        out: list[C.Command] = []
        for _ in range(limit):
            try:
                msg = ipc.recv(self.pull, zmq.NOBLOCK)
            except zmq.Again:
                break
            if msg is not None:
                out.append(cast(C.Command, msg))
        return out

    def refused(self, source: str, code: str, message: str) -> None:
        """The core refused an input's command (head not active, ...): logged, rate-limited."""
        self.refusals.setdefault(source, Refusals(source)).refuse(code, message)

    def described(self) -> dict[str, dict[str, object]]:
        """Where each input listens (ports as bound), for ``hello``."""
        return {inp.name: dict(inp.bound) for inp in self.inputs}

    def stats(self) -> dict[str, Mapping[str, object]]:
        """Each input's counters (packets, refusals...), for ``status``."""
        return {inp.name: inp.stats() for inp in self.inputs}

    def close(self) -> None:
        for inp in self.inputs:
            try:
                inp.close()
            except Exception:  # one input failing to close must not keep the others open
                import logging

                logging.getLogger(__name__).exception("closing the %s input failed", inp.name)
        self._push.close(0)
        self.pull.close(0)
