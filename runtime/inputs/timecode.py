"""The MIDI timecode input: mido's TCP MIDI port server (``mido.sockets``) or a named MIDI port, on a thread.

``bind = "127.0.0.1:5004"``: a timecode generator connects (``mido.sockets.connect``) and sends quarter-frame and
full-frame messages; there is no ALSA sequencer to rely on, so this is the transport the tests use. ``midi_port =
"NAME"``: a MIDI input port opened through mido's backend (python-rtmidi, when installed). Samples assembled by
:class:`runtime.inputs.mtc.MtcAssembler` become timecode commands; the chase itself runs in the control core.
"""

from __future__ import annotations

import select
import threading
import time
from collections.abc import Callable
from typing import Any

import mido
import mido.sockets

from runtime.core import commands as C
from runtime.inputs.config import TimecodeConfig
from runtime.inputs.mtc import MtcAssembler, MtcError, TimecodeSample
from runtime.inputs.refusals import Refusals, log


class TimecodeInput:
    """Listens for MIDI timecode and emits a command per sample (one every two frames, and every locate)."""

    name = "timecode"

    def __init__(self, cfg: TimecodeConfig, emit: Callable[[C.Command], None]) -> None:
        self.cfg = cfg
        self.emit = emit
        self.refusals = Refusals("timecode")
        self.messages = 0
        self.samples = 0
        self.bound: dict[str, Any] = {}
        self._server: Any = None
        self._port: Any = None
        self._run = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self.cfg.bind is not None:
            self._server = mido.sockets.PortServer(*self.cfg.bind)
            host, port = self._server._socket.getsockname()[:2]  # port 0: the one the system chose
            self.bound = {"bind": f"{host}:{port}", "transport": "mido.sockets (TCP MIDI)"}
            self._run = True
            self._thread = threading.Thread(target=self._serve, name="likeness-mtc", daemon=True)
            self._thread.start()
        else:
            assembler = MtcAssembler()
            self._port = mido.open_input(self.cfg.midi_port,
                                         callback=lambda msg: self._message(assembler, msg, "midi port"))
            self.bound = {"midi_port": self.cfg.midi_port}

    def close(self) -> None:
        self._run = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._server is not None:
            self._server.close()
        if self._port is not None:
            self._port.close()

    def stats(self) -> dict[str, Any]:
        return {"messages": self.messages, "samples": self.samples, "refused": self.refusals.snapshot(), **self.bound}

    def _serve(self) -> None:
        """Accept generators and read their messages (each connection assembles its own quarter frames)."""
        server = self._server
        conns: list[tuple[Any, MtcAssembler, str]] = []
        while self._run:
            socks = [server._socket] + [c[0]._socket for c in conns]
            try:
                readable, _, _ = select.select(socks, [], [], 0.2)
            except (OSError, ValueError):
                conns = [c for c in conns if not c[0].closed]
                continue
            if server._socket in readable:
                port = server.accept(block=False)
                if port is not None:
                    conns.append((port, MtcAssembler(), f"{port.name}"))
                    log.info("timecode generator connected: %s", port.name)
            for conn in list(conns):
                port, assembler, peer = conn
                if port._socket not in readable:
                    continue
                try:
                    for msg in port.iter_pending():
                        self._message(assembler, msg, peer)
                except (OSError, ValueError):  # the generator went away mid-read
                    port.close()
                if port.closed:
                    conns.remove(conn)
                    log.info("timecode generator disconnected: %s", peer)
        for port, _, _ in conns:
            port.close()

    def _message(self, assembler: MtcAssembler, msg: mido.Message, peer: str) -> None:
        received = time.monotonic()
        self.messages += 1
        try:
            sample = assembler.feed(msg, received)
        except MtcError as exc:
            self.refusals.refuse("not timecode", f"{exc} (from {peer})")
            return
        if sample is not None:
            self.samples += 1
            self.emit(_command(sample))


def _command(s: TimecodeSample) -> C.Timecode:
    return C.Timecode(0, s.seconds, s.fps, s.rate, s.label, s.received, s.full)
