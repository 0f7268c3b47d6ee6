"""The loop process ⇄ API server process link: pickled messages over a ZeroMQ PAIR socket, and a shared e-stop flag.

Messages are pickled with protocol 5 and their large buffers (compiled clips, frame arrays) travel as separate
frames, so unpickling in the loop process copies nothing big. The e-stop flag is a counter in shared memory: the API
server (and a signal handler) increment it, the control loop compares it with the last value it saw every cycle, so
an e-stop reaches the core within one cycle whatever is queued on the link.
"""

from __future__ import annotations

import contextlib
import pickle
import struct
from multiprocessing import shared_memory
from typing import Any

import zmq

_COUNTER = struct.Struct("<Q")
_REASON = struct.Struct("<B63s")  # length, then the reason of the latest trip (UTF-8, truncated)


def send(sock: zmq.Socket, obj: Any, flags: int = 0) -> None:
    """Pickle ``obj`` (protocol 5, out-of-band buffers as extra frames) and send it."""
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    sock.send_multipart([head, *buffers], flags, copy=len(buffers) == 0)


def recv(sock: zmq.Socket, flags: int = 0) -> Any:
    """Receive one message sent by :func:`send` (``zmq.Again`` with NOBLOCK and nothing waiting)."""
    frames = sock.recv_multipart(flags, copy=False)
    return pickle.loads(frames[0].buffer, buffers=[f.buffer for f in frames[1:]])


class EStopFlag:
    """A shared counter: :meth:`trip` adds one, :meth:`tripped` tells the loop whether it moved since last time, and
    :meth:`reason` what the latest trip gave as its reason."""

    def __init__(self, name: str | None = None) -> None:
        if name is None:
            self._shm = shared_memory.SharedMemory(create=True, size=_COUNTER.size + _REASON.size)
            self._owner = True
            _COUNTER.pack_into(self._shm.buf, 0, 0)
        else:
            self._shm = shared_memory.SharedMemory(name=name)
            self._owner = False
            # Python 3.11 registers attached segments with this process's resource tracker, which would unlink
            # the owner's segment when this process exits: only the owner cleans up.
            with contextlib.suppress(Exception):
                from multiprocessing import resource_tracker

                resource_tracker.unregister(self._shm._name, "shared_memory")  # type: ignore[attr-defined]
        self._last = self.value()

    @property
    def name(self) -> str:
        return self._shm.name

    def value(self) -> int:
        return _COUNTER.unpack_from(self._shm.buf, 0)[0]

    def trip(self, reason: str = "api") -> None:
        """Raise the flag with ``reason`` (one writer at a time per process; increments from two processes may merge
        into one, which still reads as tripped). The reason is written before the counter moves."""
        raw = reason.encode("utf-8", "replace")[:63]
        _REASON.pack_into(self._shm.buf, _COUNTER.size, len(raw), raw)
        _COUNTER.pack_into(self._shm.buf, 0, self.value() + 1)

    def reason(self) -> str:
        """The reason given by the latest trip ("api" before any)."""
        n, raw = _REASON.unpack_from(self._shm.buf, _COUNTER.size)
        return raw[:n].decode("utf-8", "replace") if n else "api"

    def tripped(self) -> bool:
        """True once per change of the counter since the previous call."""
        v = self.value()
        if v != self._last:
            self._last = v
            return True
        return False

    def close(self) -> None:
        try:
            self._shm.close()
        finally:
            if self._owner:
                with contextlib.suppress(FileNotFoundError):
                    self._shm.unlink()
