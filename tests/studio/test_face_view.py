"""The face view: Loop subdivision as a matrix, per-vertex interpolated strain colours, and the socket that carries
frames and timeline requests to and from the page (a real WebSocket client on loopback)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from studio.faceview import ColorRamp, ramp
from studio.skinsocket import FRAME, MESH, SkinSocket, pack
from studio.subdivide import loop_step, loop_subdivision
from tests._wait import wait_until

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


@pytest.fixture(scope="module")
def studio_offline():
    """A studio on the sample head without a daemon (no browser)."""
    from studio.app import Studio, StudioOptions
    from studio.head import StudioHead

    s = Studio(StudioHead.load(SAMPLE), StudioOptions(port=0))
    try:
        yield s
    finally:
        s.close()


def _grid(n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A flat n×n grid of squares (two triangles each) in the z = 0 plane."""
    xs, ys = np.meshgrid(np.arange(n + 1, dtype=float), np.arange(n + 1, dtype=float))
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    f = []
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            f += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    return v, np.array(f)


def test_loop_subdivision_weights_counts_and_creases() -> None:
    v, f = _grid()
    step = loop_step(f, len(v))
    n_edges = len({tuple(sorted(e)) for tri in f for e in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))})
    assert step.matrix.shape == (len(v) + n_edges, len(v)) and len(step.faces) == 4 * len(f)
    m = step.matrix.toarray()
    assert np.allclose(m.sum(axis=1), 1.0) and m.min() >= 0.0  # affine and convex: no overshoot
    fine = step.matrix @ v
    assert np.allclose(fine[:, 2], 0.0)  # a plane stays a plane
    # The rim is a crease: fine vertices on the boundary edge y = 0 stay on it, spaced evenly (B-spline rule;
    # the two corners, where the rim turns, are rounded off it).
    rim = np.sort(fine[np.isclose(fine[:, 1], 0.0), 0])
    assert np.allclose(rim, np.arange(0.5, 3.51, 0.5))
    # Orientation is kept: every fine triangle's normal points the same way as the coarse ones (+z here).
    a, b, c = (fine[step.faces[:, k].astype(int)] for k in range(3))
    assert np.all(np.cross(b - a, c - a)[:, 2] > 0)
    two = loop_subdivision(f, len(v), 2)
    assert len(two.faces) == 16 * len(f) and np.allclose(np.asarray(two.matrix.sum(axis=1)).ravel(), 1.0)
    with pytest.raises(ValueError, match="outside"):
        loop_step(f + 100, len(v))


def test_subdivision_smooths_a_bent_surface() -> None:
    v, f = _grid(6)
    bent = v.copy()
    bent[:, 2] = np.where(v[:, 0] >= 3, v[:, 0] - 3, 0.0)  # a crease along x = 3
    fine = loop_subdivision(f, len(v), 2).matrix @ bent
    near = fine[np.abs(fine[:, 0] - 3.0) < 0.3]
    # The sharp fold (z = max(x - 3, 0)) is rounded off: above it just past the fold, never below the plane.
    assert near[:, 2].min() >= -1e-12 and np.any(near[:, 2] > np.maximum(near[:, 0] - 3.0, 0.0) + 1e-3)


def test_colour_ramp_table_matches_the_interpolation() -> None:
    stops, colours = [0.0, 0.5, 1.0], [(0, 0, 0), (100, 200, 0), (255, 0, 0)]
    lut = ColorRamp(stops, colours)
    u = np.linspace(-0.5, 1.5, 101)
    assert np.abs(lut(u) - ramp(np.clip(u, 0, 1), stops, colours)).max() <= 255 / 1024 * 2 + 1e-6


def test_face_view_colours_are_interpolated_per_vertex(studio_offline) -> None:
    view = studio_offline.view
    skin = studio_offline.skin
    head = studio_offline.head
    p = head.neutral.copy()
    p[head.names.index("jaw")] = head.hi[head.names.index("jaw")]
    frame = skin.frame(p)
    vmax = view.vertex_max(frame.face_utilisation)
    u = frame.face_utilisation
    worst = int(np.nanargmax(u))
    assert np.all(vmax[skin.faces[worst].astype(int)] == pytest.approx(u[worst]))  # the worst triangle stays seen
    pos, col = view.fine(frame.positions, vmax, view.strain_ramp)
    assert pos.shape == (view.sub.n_vertices, 3) and col.shape == pos.shape and col.dtype == np.uint8
    assert np.allclose(pos[: len(frame.positions)], view.sub.matrix[: len(frame.positions)] @ frame.positions,
                       atol=1e-5)
    # Interpolated, not per-triangle patches: far more distinct colours than the five strain bands, and the
    # refused region is red.
    assert len(np.unique(col, axis=0)) > 50
    assert np.any(np.all(col == (215, 35, 35), axis=1))
    # The exact pose's error map: the vertex distance in mm on its own continuous scale (1.5 mm: between the 1 mm
    # and 2 mm stops, teal to green).
    worst, mean = view.show_error(frame.positions + np.array([0.0, 0.0015, 0.0]), frame.positions)
    assert worst == pytest.approx(1.5, abs=1e-3) and mean == pytest.approx(1.5, abs=1e-3)
    _, err_col = view.fine(frame.positions, np.full(len(frame.positions), 1.5), view.error_ramp)
    assert np.all(err_col == err_col[0]) and tuple(err_col[0]) == (80, 180, 130)


def test_socket_sends_the_mesh_first_then_the_newest_frame_and_answers_requests() -> None:
    from websockets.sync.client import connect

    faces = np.array([[0, 1, 2]], dtype=np.uint32)
    pos = np.eye(3, dtype=np.float32)
    col = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], dtype=np.uint8)
    sock = SkinSocket("127.0.0.1")
    sock.first_message = lambda: pack(MESH, pos, col, 1, faces)
    seen: list[dict] = []

    def handler(request: dict, reply) -> None:
        seen.append(request)
        reply({"type": "echo", "op": request["op"]})

    sock.on_request(handler)
    sock.start()
    sock.publish("timeline", {"tracks": []})
    try:
        with connect(f"ws://127.0.0.1:{sock.port}", compression=None) as ws:
            first = ws.recv(timeout=10)
            kind, nv, nf, seq = struct.unpack_from("<4I", first)
            assert (kind, nv, nf, seq) == (MESH, 3, 1, 1)
            assert np.array_equal(np.frombuffer(first, "<f4", 9, 16).reshape(3, 3), pos)
            assert np.array_equal(np.frombuffer(first, np.uint8, 9, 52).reshape(3, 3), col)
            assert np.array_equal(np.frombuffer(first, "<u4", 3, 64), faces.ravel())
            assert json.loads(ws.recv(timeout=10)) == {"type": "timeline", "tracks": []}  # late joiners get it
            assert wait_until(lambda: len(sock._peers) == 1, 10)
            sock.send_frame(pack(FRAME, pos * 2, col, 2))
            kind, nv, nf, seq = struct.unpack_from("<4I", ws.recv(timeout=10))
            assert (kind, nv, nf, seq) == (FRAME, 3, 0, 2)
            ws.send(json.dumps({"op": "undo"}))
            assert json.loads(ws.recv(timeout=10)) == {"type": "echo", "op": "undo"}
            ws.send("not json")
            assert json.loads(ws.recv(timeout=10))["error"] == "request is not JSON"
        assert seen == [{"op": "undo"}]
    finally:
        sock.stop()


def test_a_frame_sender_waits_until_the_frame_is_on_its_way() -> None:
    from websockets.sync.client import connect

    pos = np.eye(3, dtype=np.float32)
    col = np.zeros((3, 3), dtype=np.uint8)
    sock = SkinSocket("127.0.0.1")
    sock.start()
    try:
        with connect(f"ws://127.0.0.1:{sock.port}", compression=None) as ws:
            assert wait_until(lambda: len(sock._peers) == 1, 10)
            peer = next(iter(sock._peers))
            sock.send_frame(pack(FRAME, pos, col, 7), wait_s=10.0)
            assert peer.sent == peer.offered == 1  # sent before send_frame returned
            assert struct.unpack_from("<4I", ws.recv(timeout=10))[3] == 7
    finally:
        sock.stop()


def test_the_page_learns_each_pose_slider_and_a_value_on_the_socket_poses_the_skin(studio_offline) -> None:
    """The page computes a slider's new value from a key or the pointer itself (it needs each pose slider's range
    and step, published on the socket) and sends it there; the studio poses at once and sends the frame."""
    from websockets.sync.client import connect

    studio = studio_offline
    head = studio.head
    jaw = head.by_name["jaw"]
    k = head.names.index("jaw")
    studio.set_pose(head.neutral.copy())
    with connect(f"ws://127.0.0.1:{studio.socket.port}", compression=None) as ws:
        specs = None
        while specs is None:
            msg = ws.recv(timeout=10)
            if isinstance(msg, str) and json.loads(msg).get("type") == "sliders":
                specs = json.loads(msg)["sliders"]
        s = studio.pose_tab.sliders["jaw"]
        assert specs["jaw"] == [s.min, s.max, s.step] and set(specs) == set(studio.pose_tab.sliders)
        assert wait_until(lambda: len(studio.socket._peers) == 1, 10)
        ws.send(json.dumps({"op": "slider", "name": "jaw", "value": s.max}))
        assert wait_until(lambda: abs(np.degrees(studio.p[k]) - jaw.max) < 1e-6, 10)
        while True:  # the frame of the new pose: the fine surface moved by the simulated one
            msg = ws.recv(timeout=10)
            if isinstance(msg, bytes) and struct.unpack_from("<4I", msg)[0] == FRAME:
                nv = struct.unpack_from("<4I", msg)[1]
                got = np.frombuffer(msg, "<f4", nv * 3, 16).reshape(nv, 3)
                want = studio.view.sub.matrix @ studio.skin.frame(studio.p).positions
                if np.allclose(got, want, atol=1e-5):
                    break
        ws.send(json.dumps({"op": "slider", "name": "not-a-channel", "value": 1.0}))  # ignored, not an error
        ws.send(json.dumps({"op": "slider", "name": "jaw", "value": -1e9}))  # clamped to the slider's range
        assert wait_until(lambda: abs(np.degrees(studio.p[k]) - jaw.min) < 1e-6, 10)
