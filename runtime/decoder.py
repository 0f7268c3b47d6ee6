"""The API server's decoder process: large requests (clips, stream batches) are decoded, validated and compiled here.

A request larger than ``inline_bytes`` would hold the server's thread (and the GIL) for milliseconds; in a process of
its own it cannot delay an e-stop. The server hands over a :class:`DecodeJob` (PUSH) and gets back a
:class:`Decoded` (PULL): the ready core command, or the error reply to send. :class:`DecoderProcess` is the server's
end; :func:`decoder_main` runs in the child (``python -m runtime.decoder IN OUT``, its :class:`DecoderSpec` pickled
on standard input).
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass

import zmq

from models import errors as E
from models import protocol as P
from runtime import ipc
from runtime import messages as M
from runtime.core.channels import ChannelMap
from runtime.core.commands import Command
from runtime.requests import LocalRequest, to_command
from runtime.wire_scan import RequestId

log = logging.getLogger(__name__)

#: A reply as the protocol packs it (``{"id", "ok", ...}`` or a structured error).
ReplyMap = dict[str, object]


@dataclass(frozen=True)
class DecoderSpec:
    """What the decoder process needs, picklable: the head's channels, the default pose speed, the size limit."""

    channels: ChannelMap
    safe_speed: float  # [safety] safe_speed: the default speed of a pose
    inline_bytes: int  # requests up to this size are decoded by the server itself


@dataclass(frozen=True)
class DecodeJob:
    """Server → decoder: one raw request, its reply envelope and the token its command will carry."""

    token: int
    envelope: list[bytes]
    payload: bytes
    received: float  # when it reached the daemon (monotonic)


@dataclass(frozen=True)
class Decoded:
    """Decoder → server: the job's request id and op, and either its command or the error reply to send."""

    token: int
    envelope: list[bytes]
    received: float
    request_id: RequestId | None
    op: str
    command: Command | None
    error: ReplyMap | None


def decode(job: DecodeJob, spec: DecoderSpec) -> Decoded:
    """Decode, validate and compile one request; every problem becomes the error reply to send."""
    rid: RequestId | None = None

    def failed(request_id: RequestId | None, exc: BaseException) -> Decoded:
        return Decoded(job.token, job.envelope, job.received, request_id, "", None, P.reply_for(request_id, exc))

    try:
        req = M.decode_request(job.payload)
        rid, op = req.id, type(req).__struct_config__.tag
        if isinstance(req, LocalRequest):
            raise E.TooLarge(f"a {op} request needs no more than {spec.inline_bytes} bytes")
        cmd = to_command(req, job.token, spec.channels, spec.safe_speed, job.received)
        return Decoded(job.token, job.envelope, job.received, rid, op, cmd, None)
    except M.RequestError as exc:
        return failed(exc.request_id, exc)
    except E.LikenessError as exc:
        return failed(rid, exc)
    except Exception as exc:
        log.exception("internal error decoding a request")
        return failed(rid, exc)


def decoder_main(spec: DecoderSpec, endpoint_in: str, endpoint_out: str) -> None:
    """The decoder process: serve jobs until the server process goes away."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent()
    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.connect(endpoint_in)
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    push.connect(endpoint_out)
    parent = os.getppid()
    try:
        while os.getppid() == parent:
            if not pull.poll(200):
                continue
            job = ipc.recv(pull)
            if isinstance(job, DecodeJob):
                ipc.send(push, decode(job, spec))
    finally:
        pull.close(0)
        push.close(0)
        ctx.term()


def die_with_parent() -> None:
    """Ask the kernel to end this process when its parent dies (Linux), so no child outlives a ``kill -9``."""
    with contextlib.suppress(Exception):
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class DecoderProcess:
    """The server's end of the decoder process: :meth:`submit` a job, :attr:`results` to poll, :meth:`drain`."""

    def __init__(self, ctx: zmq.Context, spec: DecoderSpec) -> None:
        self._tmp = tempfile.mkdtemp(prefix="likeness-api-")
        self._jobs = ctx.socket(zmq.PUSH)
        self._jobs.setsockopt(zmq.LINGER, 0)
        self._jobs.bind(f"ipc://{self._tmp}/in")
        self.results = ctx.socket(zmq.PULL)
        self.results.bind(f"ipc://{self._tmp}/out")
        self._process = subprocess.Popen([sys.executable, "-m", "runtime.decoder", f"ipc://{self._tmp}/in",
                                          f"ipc://{self._tmp}/out"], stdin=subprocess.PIPE)
        assert self._process.stdin is not None
        self._process.stdin.write(pickle.dumps(spec))
        self._process.stdin.close()

    def submit(self, job: DecodeJob) -> None:
        """Queue a request for decoding."""
        ipc.send(self._jobs, job)

    def drain(self, limit: int = 100) -> list[Decoded]:
        """The results ready now (never waits)."""
        out = []
        for _ in range(limit):
            try:
                msg = ipc.recv(self.results, zmq.NOBLOCK)
            except zmq.Again:
                break
            if isinstance(msg, Decoded):
                out.append(msg)
        return out

    def close(self) -> None:
        """Stop the process and remove its sockets."""
        self._process.terminate()
        try:
            self._process.wait(2.0)
        except Exception:
            self._process.kill()
        shutil.rmtree(self._tmp, ignore_errors=True)
        self._jobs.close(0)
        self.results.close(0)


if __name__ == "__main__":
    # The messages' classes are this module's under its own name (not ``__main__``), as the server pickles them.
    from runtime.decoder import decoder_main as _main

    _main(pickle.loads(sys.stdin.buffer.read()), sys.argv[1], sys.argv[2])
