"""The loop process ⇄ API server process pipe: pickled messages, and a shared e-stop flag.

Commands (server → loop) travel over a named pipe (:class:`PipeWriter` → :class:`PipeReader`): a write from the
server's thread wakes the loop's realtime thread directly, without ZeroMQ's I/O threads in between (two thread
hand-offs at normal priority, which cost 0.1–1 ms per command on a busy two-core machine). Everything else (loop →
server: replies, events, state snapshots) uses a ZeroMQ PAIR socket (:func:`send`, :func:`recv`). This module moves
bytes; what the messages are is :mod:`runtime.loop_messages` (the pipe is typed by its message type:
``PipeWriter[Command]``). Messages are pickled with protocol 5 and their large buffers (compiled clips, frame
arrays) travel out of band, so unpickling in the loop process copies nothing big. The e-stop flag is a counter in
shared memory: the API server (and a signal handler) increment it, the control loop compares it with the last value
it saw every cycle, so an e-stop reaches the core within one cycle whatever is queued on the command pipe.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import itertools
import os
import pickle
import struct
from collections.abc import Callable
from multiprocessing import shared_memory
from typing import Generic, TypeVar, cast

import zmq

_COUNTER = struct.Struct("<Q")
_HEADER = struct.Struct("<QI")  # body length, number of out-of-band buffers; then their lengths, the pickle, buffers
_LEN = struct.Struct("<Q")
#: Buffers smaller than this are pickled in band (a separate buffer costs more than copying it).
OUT_OF_BAND_BYTES = 64 * 1024
_F_SETPIPE_SZ = 1031  # Linux: the pipe's kernel buffer size
_REASON = struct.Struct("<B63s")  # length, then the reason of the latest trip (UTF-8, truncated)
#: The type of the messages a command pipe carries.
T = TypeVar("T")


def _out_of_band(buffers: list[pickle.PickleBuffer]) -> Callable[[pickle.PickleBuffer], bool]:
    """A pickle ``buffer_callback``: buffers of ``OUT_OF_BAND_BYTES`` or more travel out of band (appended to
    ``buffers``), smaller ones in the pickle (a separate buffer costs more than copying it)."""

    def callback(buf: pickle.PickleBuffer) -> bool:
        if buf.raw().nbytes < OUT_OF_BAND_BYTES:
            return True
        buffers.append(buf)
        return False

    return callback


def send(sock: zmq.Socket, obj: object, flags: int = 0) -> None:
    """Pickle ``obj`` (protocol 5, large buffers out of band as extra frames, sent without copying) and send it."""
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(obj, protocol=5, buffer_callback=_out_of_band(buffers))
    if buffers:
        sock.send_multipart([head, *buffers], flags, copy=False)
    else:
        sock.send(head, flags)


def recv(sock: zmq.Socket, flags: int = 0) -> object:
    """Receive one message sent by :func:`send` (``zmq.Again`` with NOBLOCK and nothing waiting)."""
    frames = sock.recv_multipart(flags, copy=False)
    if len(frames) == 1:
        return pickle.loads(frames[0].bytes)
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


# ---------------------------------------------------------------------------------------------------- command pipe
def make_pipe(path: str) -> None:
    """Create the named pipe at ``path`` (the reader opens it first, then the writer)."""
    os.mkfifo(path, 0o600)


#: A message up to this size goes into the pipe in one write (copied once); larger ones part by part, uncopied.
WHOLE_WRITE_BYTES = 64 * 1024


class PipeWriter(Generic[T]):
    """The sending end of a command pipe, for messages of type ``T``. :meth:`send` never blocks: what the pipe
    cannot take now waits in a queue (in order) until :meth:`flush`, which the owner calls when :meth:`fileno` is
    writable (``wants_write``)."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        with contextlib.suppress(OSError):  # a larger kernel buffer where allowed (default 64 KiB)
            fcntl.fcntl(self.fd, _F_SETPIPE_SZ, 1 << 20)
        self._queue: collections.deque[memoryview] = collections.deque()
        self.queued_bytes = 0

    def fileno(self) -> int:
        return self.fd

    @property
    def wants_write(self) -> bool:
        return bool(self._queue)

    def send(self, obj: T) -> None:
        """Queue ``obj`` (pickled, large buffers out of band) and write as much as the pipe takes now."""
        buffers: list[pickle.PickleBuffer] = []
        head = pickle.dumps(obj, protocol=5, buffer_callback=_out_of_band(buffers))
        parts = [memoryview(head), *(b.raw() for b in buffers)]
        sizes = [p.nbytes for p in parts]
        prefix = _HEADER.pack(sum(sizes) + _LEN.size * len(parts), len(buffers)) + b"".join(
            _LEN.pack(n) for n in sizes)
        if sum(sizes) <= WHOLE_WRITE_BYTES:  # one write: the reader wakes once, to a whole message
            parts = [memoryview(b"".join((prefix, *parts)))]
            prefix = b""
        for part in (memoryview(prefix), *parts):
            if not part.nbytes:
                continue
            mv = part.cast("B") if part.format != "B" else part
            self._queue.append(mv)
            self.queued_bytes += mv.nbytes
        self.flush()

    def flush(self) -> None:
        """Write queued bytes until the pipe is full (``BrokenPipeError`` when the reader is gone)."""
        q = self._queue
        while q:
            mv = q[0]
            try:
                n = os.write(self.fd, mv)
            except BlockingIOError:
                return
            except InterruptedError:
                continue
            self.queued_bytes -= n
            if n == mv.nbytes:
                q.popleft()
            else:
                q[0] = mv[n:]

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)


class PipeReader(Generic[T]):
    """The receiving end of a command pipe (messages of type ``T``): :meth:`recv` returns the messages complete so
    far without blocking, reading at most ``max_bytes`` per call so a large message costs several short calls rather
    than one long one."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        self._file = os.fdopen(self.fd, "rb", buffering=0, closefd=True)
        self._head = bytearray()  # the header and length table being read
        self._need = _HEADER.size
        self._body: bytearray | None = None
        self._lens: list[int] = []
        self._total = 0  # bytes of the message body being read
        self._got = 0
        self.closed = False  # the writer went away (end of file)

    def fileno(self) -> int:
        return self.fd

    def recv(self, max_messages: int = 64, max_bytes: int = 256 * 1024) -> list[T]:
        """The messages complete so far, at most ``max_messages``, reading at most ``max_bytes``."""
        out: list[T] = []
        budget = max_bytes
        while len(out) < max_messages and budget > 0:
            if self._body is None:
                try:
                    chunk = os.read(self.fd, self._need - len(self._head))
                except BlockingIOError:
                    return out
                except InterruptedError:
                    continue
                if not chunk:
                    self.closed = True
                    return out
                budget -= len(chunk)
                self._head += chunk
                if len(self._head) < self._need:
                    continue
                if self._need == _HEADER.size:
                    body_len, nbuf = _HEADER.unpack(self._head)
                    self._need = _HEADER.size + _LEN.size * (nbuf + 1)
                    self._total = body_len - _LEN.size * (nbuf + 1)
                    continue
                self._lens = [_LEN.unpack_from(self._head, _HEADER.size + _LEN.size * i)[0]
                              for i in range((self._need - _HEADER.size) // _LEN.size)]
                self._body = bytearray(self._total)
                self._got = 0
            if self._got < len(self._body):
                try:
                    n = self._file.readinto(memoryview(self._body)[self._got:self._got + budget])
                except InterruptedError:
                    continue
                if n is None:
                    return out
                if n == 0:
                    self.closed = True
                    return out
                self._got += n
                budget -= n
                if self._got < len(self._body):
                    continue
            out.append(self._finish())
        return out

    def _finish(self) -> T:
        assert self._body is not None
        mv = memoryview(self._body)
        offsets = [0]
        for n in self._lens:
            offsets.append(offsets[-1] + n)
        parts = [mv[a:b] for a, b in itertools.pairwise(offsets)]
        self._body, self._head, self._need = None, bytearray(), _HEADER.size
        return cast(T, pickle.loads(parts[0], buffers=parts[1:]))

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._file.close()
