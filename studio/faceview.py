"""The skin shown as a face: a smooth fine surface moved by the simulated surface, coloured per vertex, sent to the
page as one binary buffer per frame.

The fine surface is a Loop subdivision of the simulated surface (:mod:`studio.subdivide`, a sparse matrix computed
once), so each frame is one sparse product. Colours are interpolated, not per-triangle patches: each simulated
vertex takes the largest strain utilisation of the measured triangles around it (so a triangle the guard would
refuse stays visible), the subdivision interpolates it, and a continuous ramp through the strain bands' colours
colours it (grey blends in where the measure leaves the skin out). The exact pose's error map does the same with the
vertex error in millimetres. Normals are recomputed per frame in the page. The page's mesh hangs under a tiny viser
node (``/skin/anchor``) so that it shares viser's world transform and camera.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import viser

from studio.skin import ERROR_COLORS, ERROR_EDGES_MM, STRAIN_COLORS, STRAIN_EDGES, UNMEASURED, SkinFrame
from studio.skinsocket import FRAME, MESH, SkinSocket, pack
from studio.subdivide import loop_subdivision

#: Where the page finds the anchor: a degenerate triangle at this point (nothing is drawn).
ANCHOR_POINT = (0.123456, -0.654321, 0.0)
#: Seconds a frame's sender waits at most for the frame to be on its way to every page before it goes on (to update
#: viser's controls): the frame first.
SEND_WAIT_S = 0.03
#: Loop subdivisions of the simulated surface (1117 → 4 288 vertices on the sample head at 1; 16 786 at 2, whose
#: 33 000 triangles slow software WebGL to 0.3–0.7 s a frame on the two-core machine).
DEFAULT_LEVELS = 1


def ramp(values: np.ndarray, stops: Sequence[float], colors: Sequence[tuple[int, int, int]]) -> np.ndarray:
    """RGB (float, 0–255) of ``values`` by piecewise-linear interpolation between ``colors`` at ``stops``."""
    v = np.asarray(values, dtype=np.float64)
    c = np.asarray(colors, dtype=np.float64)
    return np.stack([np.interp(v, stops, c[:, k]) for k in range(3)], axis=1)


#: Entries of a colour ramp's lookup table (its stops' span in this many steps).
LUT_SIZE = 1024


class ColorRamp:
    """A continuous colour map as a lookup table: :meth:`__call__` gives RGB (float32, 0–255) of values (clamped to
    the stops' span)."""

    def __init__(self, stops: Sequence[float], colors: Sequence[tuple[int, int, int]]) -> None:
        self.lo, self.hi = float(stops[0]), float(stops[-1])
        self.table = ramp(np.linspace(self.lo, self.hi, LUT_SIZE + 1), stops, colors).astype(np.float32)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        scaled = (np.asarray(values, dtype=np.float32) - self.lo) * (LUT_SIZE / (self.hi - self.lo))
        return self.table[np.clip(np.rint(scaled), 0, LUT_SIZE).astype(np.intp)]


def _strain_stops() -> tuple[list[float], list[tuple[int, int, int]]]:
    """Green up to half the range, then through the bands' colours to orange at the limit and red just past it."""
    e = STRAIN_EDGES
    stops = [0.0, e[0], e[1], e[2], e[3] - 0.01, e[3]]
    return stops, [STRAIN_COLORS[0], STRAIN_COLORS[0], STRAIN_COLORS[1], STRAIN_COLORS[2], STRAIN_COLORS[3],
                   STRAIN_COLORS[4]]


def _error_stops() -> tuple[list[float], list[tuple[int, int, int]]]:
    return [0.0, *ERROR_EDGES_MM], list(ERROR_COLORS)


class FaceView:
    """The page-owned face mesh: fine surface, per-vertex colours, frames over :class:`SkinSocket`."""

    def __init__(self, server: viser.ViserServer, socket: SkinSocket, faces: np.ndarray, n_vertices: int,
                 positions: np.ndarray, levels: int = DEFAULT_LEVELS) -> None:
        self.sub = loop_subdivision(faces, n_vertices, levels)
        self._matrix = self.sub.matrix.astype(np.float32)
        self.strain_ramp, self.error_ramp = ColorRamp(*_strain_stops()), ColorRamp(*_error_stops())
        self._cols = np.empty((n_vertices, 5), dtype=np.float32)  # x, y, z, known, value
        faces = np.asarray(faces, dtype=np.intp)
        self._n = n_vertices
        self._faces = faces
        self._seq = 0
        self._pack(FRAME, positions, np.full((n_vertices,), np.nan), self.strain_ramp)
        self.anchor = server.scene.add_mesh_simple("/skin/anchor", np.array([ANCHOR_POINT] * 3, dtype=np.float32),
                                                   np.array([[0, 1, 2]], dtype=np.uint32), color=(200, 200, 200),
                                                   cast_shadow=False, receive_shadow=False)
        self.socket = socket

    def mesh_message(self) -> bytes:
        """The first message a page gets: the fine surface's triangles with the present frame."""
        pos, col = self._last
        return pack(MESH, pos, col, self._seq, self.sub.faces)

    def vertex_max(self, face_values: np.ndarray) -> np.ndarray:
        """Per simulated vertex, the largest finite value of the triangles around it (NaN where none is finite)."""
        out = np.full(self._n, -np.inf)
        vals = np.asarray(face_values, dtype=np.float64)
        ok = np.isfinite(vals)
        for k in range(3):
            np.maximum.at(out, self._faces[ok, k], vals[ok])
        out[~np.isfinite(out)] = np.nan
        return out

    def fine(self, positions: np.ndarray, vertex_values: np.ndarray,
             colors: ColorRamp) -> tuple[np.ndarray, np.ndarray]:
        """The fine surface's positions (float32) and colours (uint8) for a simulated surface and per-vertex values
        (NaN: unmeasured, grey); one sparse product carries positions, the measured share and the values."""
        cols = self._cols
        cols[:, :3] = positions
        known = np.isfinite(vertex_values)
        cols[:, 3] = known
        cols[:, 4] = np.where(known, vertex_values, 0.0)
        out = self._matrix @ cols
        weight = out[:, 3:4]
        u = out[:, 4] / np.maximum(out[:, 3], 1e-9)
        rgb = colors(u) * weight + np.asarray(UNMEASURED, dtype=np.float32) * (1.0 - weight)
        return np.ascontiguousarray(out[:, :3]), np.clip(rgb + 0.5, 0, 255).astype(np.uint8)

    def _pack(self, kind: int, positions: np.ndarray, vertex_values: np.ndarray, colors: ColorRamp) -> bytes:
        pos, col = self.fine(positions, vertex_values, colors)
        self._seq += 1
        self._last = (pos, col)
        return pack(kind, pos, col, self._seq)

    def show_strain(self, frame: SkinFrame) -> None:
        """Show a pose's predicted surface coloured by the guard's strain utilisation."""
        self._send(self._pack(FRAME, frame.positions, self.vertex_max(frame.face_utilisation), self.strain_ramp))

    def show_error(self, predicted: np.ndarray, exact: np.ndarray) -> tuple[float, float]:
        """Show the predicted surface coloured by its distance to the exact one; the largest and mean error (mm)."""
        err_mm = np.linalg.norm(np.asarray(predicted, dtype=np.float64) - np.asarray(exact, dtype=np.float64),
                                axis=1) * 1e3
        self._send(self._pack(FRAME, predicted, err_mm, self.error_ramp))
        return float(err_mm.max()), float(err_mm.mean())

    def _send(self, message: bytes) -> None:
        self.socket.send_frame(message, wait_s=SEND_WAIT_S)
