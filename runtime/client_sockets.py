"""The API server's client-facing sockets: ROUTER for requests and PUB for telemetry, bound as ``[api]`` says.

Limits (message size, high-water marks), CURVE authentication with an allow-list of client keys when a secret key
is configured, and a warning when remote clients are allowed; the endpoints are read back as bound (a port 0
becomes a real one, which ``hello`` and the daemon report).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import zmq

from models.headspec import HeadSpec
from runtime.config import DaemonConfig, resolve

if TYPE_CHECKING:
    from zmq.auth.thread import ThreadAuthenticator

log = logging.getLogger(__name__)


@dataclass
class ClientSockets:
    """The sockets clients reach: ROUTER (requests) and PUB (telemetry), as bound, with CURVE's authenticator."""

    router: zmq.Socket
    pub: zmq.Socket
    command_endpoint: str
    telemetry_endpoint: str
    auth: ThreadAuthenticator | None

    def close(self) -> None:
        self.router.close(0)
        self.pub.close(0)
        if self.auth is not None:
            self.auth.stop()


def bind_client_sockets(ctx: zmq.Context, head: HeadSpec, cfg: DaemonConfig) -> ClientSockets:
    """The ROUTER and PUB sockets bound as ``[api]`` says (limits, CURVE with an allow-list, remote clients)."""
    api = cfg.api
    router = ctx.socket(zmq.ROUTER)
    pub = ctx.socket(zmq.PUB)
    for sock in (router, pub):
        sock.setsockopt(zmq.LINGER, 0)
    router.setsockopt(zmq.MAXMSGSIZE, api.hard_max_message_bytes)
    router.setsockopt(zmq.ROUTER_MANDATORY, 0)
    router.setsockopt(zmq.SNDHWM, 1000)
    router.setsockopt(zmq.RCVHWM, 1000)
    pub.setsockopt(zmq.SNDHWM, 1000)
    auth = None
    if api.curve_secret_key:
        from zmq.auth import load_certificate
        from zmq.auth.thread import ThreadAuthenticator

        base = head.source.parent
        public, secret = load_certificate(str(resolve(base, api.curve_secret_key)))
        if secret is None:
            raise ValueError(f"api.curve_secret_key: {api.curve_secret_key} holds no secret key")
        auth = ThreadAuthenticator(ctx)
        auth.start()
        auth.configure_curve(domain="*", location=str(resolve(base, api.curve_allow_dir)))
        for sock in (router, pub):
            sock.curve_secretkey = secret
            sock.curve_publickey = public
            sock.curve_server = True
    if api.allow_remote:
        log.warning("remote clients allowed on %s: %s", api.command, "CURVE authentication with an allow-list"
                    if api.curve_secret_key else "NO authentication, plain text (insecure_remote = true)")
    router.bind(api.command)
    pub.bind(api.telemetry)
    return ClientSockets(router, pub, router.getsockopt_string(zmq.LAST_ENDPOINT),
                         pub.getsockopt_string(zmq.LAST_ENDPOINT), auth)
