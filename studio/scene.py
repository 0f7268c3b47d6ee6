"""The 3D view: the skin as one single-colour mesh per colour band, drawn by the browser (WebGL, three.js via viser).

A colour map over triangles becomes a handful of meshes that share the vertex positions and split the triangles
between them; a pose update sends the new positions and each band's triangles in one atomic batch, so the
browser never draws half an update. Bands without triangles are hidden.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import viser

from studio.skin import ERROR_COLORS, STRAIN_COLORS, UNMEASURED, SkinFrame, SkinView

RGB = tuple[int, int, int]


class BandedSkin:
    """Band meshes under ``/skin`` in a viser scene."""

    def __init__(self, server: viser.ViserServer, positions: np.ndarray, faces: np.ndarray, n_bands: int) -> None:
        self.server = server
        self._faces = np.asarray(faces, dtype=np.uint32)
        self._handles: list[viser.MeshHandle] = []
        pos = np.asarray(positions, dtype=np.float32)
        for b in range(n_bands):
            h = server.scene.add_mesh_simple(f"/skin/band{b}", pos, self._faces[:1], color=(200, 200, 200),
                                             side="double", visible=False, cast_shadow=False, receive_shadow=False)
            self._handles.append(h)
        self._shown: list[np.ndarray | None] = [None] * n_bands

    @property
    def handles(self) -> tuple[viser.MeshHandle, ...]:
        """The band meshes, in band order."""
        return tuple(self._handles)

    def show(self, positions: np.ndarray, band_faces: Sequence[np.ndarray], colors: Sequence[RGB]) -> None:
        """Draw the surface ``positions`` (V, 3) with each band's triangles in its colour."""
        if len(band_faces) != len(self._handles) or len(colors) != len(self._handles):
            raise ValueError(f"need {len(self._handles)} bands and colours, got {len(band_faces)} and {len(colors)}")
        pos = np.asarray(positions, dtype=np.float32)
        with self.server.atomic():
            for b, (h, faces, color) in enumerate(zip(self._handles, band_faces, colors, strict=True)):
                if len(faces) == 0:
                    if h.visible:
                        h.visible = False
                    self._shown[b] = None
                    continue
                faces = np.asarray(faces, dtype=np.uint32)
                prev = self._shown[b]
                if prev is None or prev.shape != faces.shape or not np.array_equal(prev, faces):
                    h.faces = faces
                    self._shown[b] = faces
                h.vertices = pos
                if tuple(h.color) != tuple(color):
                    h.color = color
                if not h.visible:
                    h.visible = True


class BandedView:
    """The skin as simulation triangles in viser's scene (one mesh per colour band): the studio's first view, kept
    for comparison (``--skin-view bands``; the latency benchmark measures it beside the face view)."""

    def __init__(self, server: viser.ViserServer, skin: SkinView, positions: np.ndarray) -> None:
        self.skin = skin
        self.bands = BandedSkin(server, positions, skin.faces, len(STRAIN_COLORS) + 1)

    def show_strain(self, frame: SkinFrame) -> None:
        self.bands.show(frame.positions, frame.band_faces, (*STRAIN_COLORS, UNMEASURED))

    def show_error(self, predicted: np.ndarray, exact: np.ndarray) -> tuple[float, float]:
        bands, worst, mean = self.skin.error_bands(exact, predicted)
        self.bands.show(predicted, [*bands, np.zeros((0, 3), dtype=np.uint32)], (*ERROR_COLORS, (0, 0, 0)))
        return worst, mean
