"""The studio: a viser page with Pose, Animate and Perform tabs and an E-stop above them, served by the front door.

:class:`Studio` owns the pose being shown (actuator values, SI), the clip being edited and, with ``--daemon``, the
link to the daemon. Each tab is a small class in its own module that adds its controls and calls back here.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import viser

from studio.clipdoc import ClipDoc
from studio.daemon_client import DaemonConnection
from studio.faceview import FaceView
from studio.frontdoor import FrontDoor
from studio.head import StudioHead
from studio.scene import BandedView
from studio.skin import SkinFrame, SkinView
from studio.skinsocket import SkinSocket

#: The skin views a studio can show (``StudioOptions.skin_view``).
SKIN_VIEWS = ("face", "bands")

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StudioOptions:
    """Where the studio serves and what it talks to."""

    host: str = "127.0.0.1"
    port: int = 8080
    daemon: str | None = None  # the daemon's command endpoint; None: offline, on the predictor alone
    telemetry: str | None = None  # the daemon's telemetry endpoint (default: the one ``hello`` names)
    client_key: str | None = None
    server_key: str | None = None
    clips_dir: Path = Path("clips")
    skin_view: str = "face"  # "face": the page-owned smooth mesh; "bands": viser scene meshes per strain band
    subdivisions: int = 1  # Loop subdivisions of the simulated surface for the face view


class Studio:
    """The running studio; :meth:`url` is the address to open, :meth:`close` stops everything it started."""

    def __init__(self, head: StudioHead, options: StudioOptions) -> None:
        from studio.animate_tab import AnimateTab
        from studio.perform_tab import PerformTab
        from studio.pose_tab import PoseTab

        self.head = head
        self.options = options
        self.skin = SkinView(head)
        self.doc = ClipDoc("take")
        self.p = head.neutral.copy()  # the pose shown, SI, head actuator order
        self.pose_lock = threading.RLock()
        #: Until this monotonic time a slider is being moved: the studio's other page updates (the Perform tab's
        #: mirror) wait, so that the skin's frames meet a free page and a free server.
        self.posing_until = 0.0
        self.daemon: DaemonConnection | None = None
        if options.daemon:
            self.daemon = DaemonConnection(options.daemon, options.telemetry, options.client_key, options.server_key)
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own address; the page's is ours
            self.server = viser.ViserServer(host=options.host, port=0, label="Likeness Studio", verbose=False)
        self.server.gui.configure_theme(control_width="large", show_logo=False,
                                        show_share_button=False, dark_mode=False)
        self.server.gui.main_panel.dock_right()
        self.server.scene.set_up_direction("+y")
        # No shadows: a face lit from the front gains little from them, and viser's shadow-casting default lights
        # (cascaded shadow maps) multiply the cost of every frame in a software renderer.
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        self._setup_camera()
        self.server.scene.add_light_directional("/light", color=(255, 255, 255), intensity=2.0,
                                                position=(0.0, 1.0, 1.0))
        first = self.skin.frame(self.p)
        if options.skin_view not in SKIN_VIEWS:
            raise ValueError(f"skin view must be one of {', '.join(SKIN_VIEWS)}, got {options.skin_view!r}")
        self.view: FaceView | BandedView
        # The page's own socket: the skin's frames (face view) and the timeline editor.
        self.socket = SkinSocket(options.host)
        if options.skin_view == "face":
            face = FaceView(self.server, self.socket, self.skin.faces, head.predictor.n_vertices, first.positions,
                            options.subdivisions)
            self.socket.first_message = face.mesh_message
            self.view = face
        else:
            self.view = BandedView(self.server, self.skin, first.positions)

        gui = self.server.gui
        self.estop_button = gui.add_button("E-stop", color="red", icon=viser.Icon.HAND_STOP, order=-100,
                                           hint="Latch the daemon's e-stop (motion stops, torque off)")
        self.estop_button.on_click(lambda _: self.press_estop())
        self.banner = gui.add_markdown(self._banner_text(), order=-99)
        tabs = gui.add_tab_group(order=0)
        with tabs.add_tab("Pose", viser.Icon.FACE_ID):
            self.pose_tab = PoseTab(self)
        with tabs.add_tab("Animate", viser.Icon.TIMELINE):
            self.animate_tab = AnimateTab(self)
        with tabs.add_tab("Perform", viser.Icon.PLAYER_PLAY):
            self.perform_tab = PerformTab(self)
        self.show_frame(first)
        self.socket.start()
        self.door = FrontDoor(options.host, options.port, self.server.get_port(), f"Likeness Studio — {head.spec.name}",
                              skin_port=self.socket.port)
        self.door.start()

    # ------------------------------------------------------------------ page
    def url(self) -> str:
        host = self.options.host if self.options.host not in ("0.0.0.0", "::") else "127.0.0.1"
        return f"http://{host}:{self.door.port}/"

    def _setup_camera(self) -> None:
        base = self.head.predictor.base_vertices
        centre = 0.5 * (base.min(axis=0) + base.max(axis=0))
        size = float(np.max(base.max(axis=0) - base.min(axis=0)))
        cam = self.server.initial_camera
        centre[1] -= 0.18 * size  # the face sits above the timeline docked under the view
        cam.look_at = tuple(float(x) for x in centre)
        cam.position = (float(centre[0] + 0.35 * size), float(centre[1] + 0.15 * size), float(centre[2] + 1.2 * size))
        cam.up = (0.0, 1.0, 0.0)

    def _banner_text(self) -> str:
        if self.daemon is None:
            return "**Offline**: posing on the skin predictor alone (start with `--daemon` to perform)."
        return f"**Daemon** `{self.daemon.endpoint}`: {self.daemon.hello.get('daemon', '')}"

    # ------------------------------------------------------------------ pose
    def set_pose(self, p: np.ndarray, source: object = None) -> SkinFrame:
        """Show actuator pose ``p`` (SI): predicted skin, strain colours, verdict; sliders follow (except
        ``source``, the control that set it)."""
        with self.pose_lock:
            self.p = np.clip(np.asarray(p, dtype=np.float64), self.head.lo, self.head.hi)
            frame = self.skin.frame(self.p)
            self.show_frame(frame)
            self.pose_tab.follow(self.p, source)
        self.server.flush()  # send now rather than at the end of viser's 1/60 s batching window
        return frame

    def show_frame(self, frame: SkinFrame) -> None:
        self.view.show_strain(frame)
        if hasattr(self, "pose_tab"):
            self.pose_tab.show_verdict(frame)

    # ------------------------------------------------------------------ daemon
    def press_estop(self) -> None:
        if self.daemon is None:
            self.notify("E-stop", "No daemon connected: nothing to stop.", "yellow")
            return
        try:
            self.daemon.estop("studio E-stop")
        except Exception as exc:  # the operator must see why the e-stop did not go through
            self.notify("E-stop failed", str(exc), "red")
            raise

    def notify(self, title: str, body: str, color: str = "blue") -> None:
        for client in self.server.get_clients().values():
            client.add_notification(title, body, color=color, auto_close_seconds=6.0)

    def close(self) -> None:
        for tab in (getattr(self, "animate_tab", None), getattr(self, "perform_tab", None),
                    getattr(self, "pose_tab", None)):
            if tab is not None:
                tab.close()
        if hasattr(self, "door"):
            self.door.stop()
        if hasattr(self, "socket"):
            self.socket.stop()
        self.server.stop()
        if self.daemon is not None:
            self.daemon.close()
