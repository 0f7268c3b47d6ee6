"""The studio's own WebSocket beside viser's: skin frames to the page as binary buffers, timeline edits both ways.

viser updates a mesh by rebuilding its scene node (a React re-render and new geometry per update, applied on the
client's next frame), which cost most of a slider move's latency. The page's script (``static/skin.js``) instead owns
one three.js mesh and writes each frame's vertex positions and colours into it; this socket carries those frames.
Each page gets a sender thread that always sends the newest frame (a slow page skips stale frames rather than
queueing them) and the newest state of each text topic (JSON, e.g. the timeline). Text messages from the page are
JSON requests handed to the registered handler, which may answer the page that sent them.

Binary messages (little-endian): a 16-byte header ``u32 kind, u32 n_vertices, u32 n_faces, u32 seq``, then
``f32 positions[n_vertices * 3]``, ``u8 colours[n_vertices * 3]`` padded to 4 bytes, and for kind 1 (the mesh,
sent first) ``u32 faces[n_faces * 3]``; kind 2 (a frame) has no faces.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.server import ServerConnection, serve

log = logging.getLogger(__name__)

MESH, FRAME = 1, 2
#: Largest request from a page (bytes): timeline edits are small JSON.
MAX_REQUEST = 1 << 20

Handler = Callable[[dict[str, Any], Callable[[dict[str, Any]], None]], None]


def pack(kind: int, positions: np.ndarray, colors: np.ndarray, seq: int, faces: np.ndarray | None = None) -> bytes:
    """One binary message (see the module's docstring)."""
    pos = np.ascontiguousarray(positions, dtype="<f4")
    col = np.ascontiguousarray(colors, dtype=np.uint8)
    if pos.ndim != 2 or pos.shape[1] != 3 or col.shape != pos.shape:
        raise ValueError(f"positions and colours must both be (V, 3), got {pos.shape} and {col.shape}")
    n_faces = 0 if faces is None else len(faces)
    parts = [struct.pack("<4I", kind, len(pos), n_faces, seq & 0xFFFFFFFF), pos.tobytes(), col.tobytes(),
             b"\0" * (-col.size % 4)]
    if faces is not None:
        parts.append(np.ascontiguousarray(faces, dtype="<u4").tobytes())
    return b"".join(parts)


class _Peer:
    """One page: the newest frame and text topics waiting to go out, and the thread that sends them."""

    def __init__(self, conn: ServerConnection) -> None:
        self.conn = conn
        self.cond = threading.Condition()
        self.binary: bytes | None = None
        self.texts: dict[str, str] = {}
        self.offered = 0  # binaries offered so far; ``sent``: the count as of the last binary sent
        self.sent = 0
        self.closed = False
        self.thread = threading.Thread(target=self._send_loop, name="studio-skin-send", daemon=True)

    def offer(self, binary: bytes | None = None, topic: str | None = None, text: str | None = None) -> int:
        """Queue the newest binary and/or a topic's text; the count of binaries offered so far."""
        with self.cond:
            if binary is not None:
                self.binary = binary
                self.offered += 1
            if topic is not None and text is not None:
                self.texts[topic] = text
            self.cond.notify_all()
            return self.offered

    def wait_sent(self, count: int, timeout: float) -> None:
        """Wait (at most ``timeout`` s) until the binary that made ``count`` offers, or a newer one, is sent."""
        with self.cond:
            self.cond.wait_for(lambda: self.closed or self.sent >= count, timeout)

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()

    def _send_loop(self) -> None:
        while True:
            with self.cond:
                while not self.closed and self.binary is None and not self.texts:
                    self.cond.wait()
                if self.closed:
                    return
                binary, self.binary = self.binary, None
                texts, self.texts = list(self.texts.values()), {}
                count = self.offered
            try:
                if binary is not None:
                    self.conn.send(binary)
                    with self.cond:
                        self.sent = count
                        self.cond.notify_all()
                for text in texts:
                    self.conn.send(text)
            except (ConnectionClosed, OSError):
                with self.cond:
                    self.closed = True
                    self.cond.notify_all()
                return


class SkinSocket:
    """WebSocket server on ``host`` (any free port) for the page's skin mesh and timeline."""

    def __init__(self, host: str) -> None:
        self.first_message: Callable[[], bytes | None] = lambda: None  # what a page gets first (the mesh)
        self._peers: set[_Peer] = set()
        self._lock = threading.Lock()
        self._handler: Handler | None = None
        self._routes: dict[str, Handler] = {}
        self._texts: dict[str, str] = {}
        self._server = serve(self._serve, host, 0, compression=None, max_size=MAX_REQUEST)
        self._thread = threading.Thread(target=self._server.serve_forever, name="studio-skin-ws", daemon=True)

    @property
    def port(self) -> int:
        return int(self._server.socket.getsockname()[1])

    def start(self) -> None:
        self._thread.start()

    def on_request(self, handler: Handler, ops: tuple[str, ...] = ()) -> None:
        """``handler(request, reply)`` runs for each JSON request from a page (on that page's thread): for requests
        whose ``op`` is in ``ops``, or, with no ``ops``, for every request no other handler takes."""
        if ops:
            self._routes.update(dict.fromkeys(ops, handler))
        else:
            self._handler = handler

    def send_frame(self, message: bytes, wait_s: float = 0.0) -> None:
        """Offer a binary frame to every page (each sends the newest it has when it is ready). With ``wait_s``, wait
        that long at most until every page's sender has sent it: the caller's next work (viser's updates, which
        hold Python's lock for milliseconds) then does not delay the frame."""
        with self._lock:
            peers = tuple(self._peers)
        counts = [(p, p.offer(binary=message)) for p in peers]
        end = time.monotonic() + wait_s
        for p, n in counts:
            left = end - time.monotonic()
            if left <= 0:
                break
            p.wait_sent(n, left)

    def publish(self, topic: str, state: dict[str, Any]) -> None:
        """Offer the newest state of ``topic`` (JSON with ``"type": topic``) to every page, and to pages that
        connect later."""
        text = json.dumps({"type": topic, **state}, separators=(",", ":"), allow_nan=False)
        with self._lock:
            self._texts[topic] = text
            peers = tuple(self._peers)
        for p in peers:
            p.offer(topic=topic, text=text)

    def _serve(self, conn: ServerConnection) -> None:
        peer = _Peer(conn)
        with self._lock:
            self._peers.add(peer)
            texts = dict(self._texts)
        peer.offer(binary=self.first_message())
        for topic, text in texts.items():
            peer.offer(topic=topic, text=text)
        peer.thread.start()

        def reply(answer: dict[str, Any]) -> None:
            peer.offer(topic=f"reply:{answer.get('type', '')}", text=json.dumps(answer, allow_nan=False))

        try:
            for message in conn:
                if isinstance(message, bytes):
                    continue
                try:
                    request = json.loads(message)
                except ValueError:
                    reply({"type": "error", "error": "request is not JSON"})
                    continue
                handler = self._routes.get(str(request.get("op"))) if isinstance(request, dict) else None
                handler = handler or self._handler
                if not isinstance(request, dict) or handler is None:
                    continue
                try:
                    handler(request, reply)
                except Exception as exc:  # the page is told; the studio keeps serving
                    log.exception("page request %r failed", request.get("op"))
                    reply({"type": "error", "error": f"{request.get('op')}: {exc}"})
        except ConnectionClosed:
            pass
        finally:
            with self._lock:
                self._peers.discard(peer)
            peer.close()

    def stop(self) -> None:
        self._server.shutdown()
        with self._lock:
            peers = tuple(self._peers)
        for p in peers:
            p.close()
