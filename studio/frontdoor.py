"""The page's front door: serves viser's client page with the studio's script added, on the studio's port.

viser serves its client from its own WebSocket port and offers no hook to add a script to the page. The studio
therefore serves the same client page itself (plain ``http.server``), adds ``<script src="/studio.js">`` (which
gives every control an accessible name and keeps the E-stop in view), and points the client at viser's WebSocket
with the client's documented ``?websocket=`` query parameter.
"""

from __future__ import annotations

import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from urllib.parse import urlsplit

#: The script every page loads (``studio/static/studio.js``).
SCRIPT_NAME = "studio.js"
#: Run before viser's client (to see three.js's scene as it is made): the page-owned skin mesh and the timeline editor.
EARLY_SCRIPTS = ("skin.js", "timeline.js")


def viser_client_page() -> str:
    """The HTML of viser's built client (one self-contained file)."""
    import viser

    path = Path(viser.__file__).resolve().parent / "client" / "build" / "index.html"
    return path.read_text(encoding="utf-8")


def studio_script(name: str = SCRIPT_NAME) -> bytes:
    return resources.files("studio").joinpath("static", name).read_bytes()


def page_with_script(html: str, title: str, early: tuple[str, ...] = ()) -> bytes:
    """The client page with the studio's script tag and title (the script runs after the client's); ``early``
    scripts run before the client's (the first thing in ``<head>``)."""
    tag = f'<script src="/{SCRIPT_NAME}" defer></script>'
    if "</head>" not in html or "<head>" not in html:
        raise ValueError("viser's client page has no <head> … </head>: cannot add the studio script")
    html = html.replace("<title>Viser</title>", f"<title>{title}</title>", 1)
    first = "".join(f'<script src="/{name}"></script>' for name in early)
    return html.replace("<head>", "<head>" + first, 1).replace("</head>", tag + "</head>", 1).encode("utf-8")


class FrontDoor:
    """HTTP server on ``host:port`` for the page; the WebSocket stays on viser's own port ``ws_port``."""

    def __init__(self, host: str, port: int, ws_port: int, title: str = "Likeness Studio",
                 skin_port: int | None = None) -> None:
        self.ws_port = ws_port
        early = EARLY_SCRIPTS if skin_port is not None else ()
        page = page_with_script(viser_client_page(), title, early)
        scripts = {f"/{SCRIPT_NAME}": studio_script()}
        for name in early:  # the page's own socket: its port goes first in each early script
            scripts[f"/{name}"] = f"window.LIKENESS_SKIN_PORT = {int(skin_port or 0)};\n".encode() + studio_script(name)
        door = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                url = urlsplit(self.path)
                if url.path in ("/", "/index.html"):
                    if "websocket=" not in url.query:
                        host_name = (self.headers.get("Host") or "127.0.0.1").rsplit(":", 1)[0]
                        self.send_response(HTTPStatus.FOUND)
                        self.send_header("Location", f"/?websocket=ws://{host_name}:{door.ws_port}")
                        self.send_header("Content-Length", "0")
                        self.end_headers()
                        return
                    self._send(page, "text/html; charset=utf-8")
                elif url.path in scripts:
                    self._send(scripts[url.path], "application/javascript")
                else:
                    self.send_error(HTTPStatus.NOT_FOUND)

            def _send(self, body: bytes, mime: str) -> None:
                self.send_response(HTTPStatus.OK)
                self.send_header("Content-Type", mime)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: object) -> None:
                pass

        self._httpd = ThreadingHTTPServer((host, port), Handler)
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, name="studio-http", daemon=True)

    @property
    def port(self) -> int:
        return int(self._httpd.server_address[1])

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()
