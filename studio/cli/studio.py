"""``likeness studio``: serve the studio page for a head, optionally connected to a running daemon.

Only the standard library is imported here; the studio itself loads when the command runs.
"""

from __future__ import annotations

import argparse
import ipaddress
import time
from pathlib import Path

SAMPLE_HEAD = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The head, the daemon to perform through, where to serve and where clips go."""
    p.description = ("Serve Likeness Studio for a head: pose it on the skin predictor, key clips, and (with --daemon) "
                     "play them on the head through the daemon's protocol.")
    p.add_argument("--config", type=Path, default=SAMPLE_HEAD, help="head spec TOML (default: the sample head)")
    p.add_argument("--daemon", default=None, metavar="tcp://HOST:PORT",
                   help="the daemon's command endpoint (without it the studio works offline on the predictor)")
    p.add_argument("--telemetry", default=None, metavar="tcp://HOST:PORT",
                   help="the daemon's telemetry endpoint (default: the one the daemon's hello names)")
    p.add_argument("--port", type=int, default=8080, help="HTTP port of the page (default 8080; 0: any free port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (default loopback; anything else needs [api] allow_remote = true and "
                        "insecure_remote = true in the head config: the page has no authentication)")
    p.add_argument("--client-key", default=None, help="CURVE client secret key file (daemon with CURVE)")
    p.add_argument("--server-key", default=None, help="CURVE server public key file (daemon with CURVE)")
    p.add_argument("--clips-dir", type=Path, default=Path("clips"), help="where 'Save clip' writes (default ./clips)")
    p.add_argument("--skin-view", choices=("face", "bands"), default="face",
                   help="face: the smooth subdivided skin in a mesh the page owns (default); bands: the simulation "
                        "triangles as viser scene meshes per strain band (slower; for comparison)")
    p.add_argument("--subdivisions", type=int, default=1, choices=range(0, 4), metavar="N",
                   help="Loop subdivisions of the simulated surface for the face view (0-3, default 1)")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_host(host: str, api: dict) -> str | None:
    """Why the page may not be served on ``host`` (None when fine): the daemon's opt-in, and then some."""
    if _is_loopback(host):
        return None
    if api.get("allow_remote") is True and api.get("insecure_remote") is True:
        return None
    return (f"--host {host} serves beyond loopback; the studio page has no authentication, so this needs "
            "[api] allow_remote = true and insecure_remote = true in the head config")


def run(args: argparse.Namespace) -> int:
    """Serve the studio until Ctrl-C."""
    from models.errors import SpecError, UsageError
    from models.headspec import load_head

    try:
        spec = load_head(args.config)
    except OSError as exc:
        raise UsageError(str(exc)) from None
    problem = check_host(args.host, dict(spec.section("api")))
    if problem:
        raise UsageError(problem)
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be 0..65535, got {args.port}")
    from models.client import DaemonError, DaemonTimeout
    from studio.app import Studio, StudioOptions
    from studio.head import StudioHead

    try:
        head = StudioHead(spec)
    except (SpecError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    options = StudioOptions(host=args.host, port=args.port, daemon=args.daemon, telemetry=args.telemetry,
                            client_key=args.client_key, server_key=args.server_key, clips_dir=args.clips_dir,
                            skin_view=args.skin_view, subdivisions=args.subdivisions)
    try:
        studio = Studio(head, options)
    except (DaemonError, DaemonTimeout) as exc:
        raise UsageError(f"daemon {args.daemon}: {exc}") from None
    except OSError as exc:
        raise UsageError(f"cannot serve on {args.host}:{args.port}: {exc}") from None
    print(f"Likeness Studio for head {spec.name!r}: {studio.url()}", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        studio.close()
    return 0
