"""OSC addresses → channels (``[inputs.osc.map]``) and control addresses, matched by python-osc's dispatcher.

``"/face/jaw" = "jaw"`` maps one address; ``"/face/arkit/*" = "arkit.*"`` maps every address under ``/face/arkit/``
to the channel named by what the ``*`` matched (``/face/arkit/jawOpen`` → ``arkit.jawOpen``). Incoming address
patterns (``/face/{jaw,brow_l}``) reach every mapped address they match, as OSC specifies.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from pythonosc.dispatcher import Dispatcher

from runtime.core.channels import ChannelMap, UnknownChannel

CONTROL_OPS = ("enable", "disable", "play", "stop", "estop")


def _noop(*_: object) -> None:
    """Handlers are looked up, never invoked: the input applies a packet's messages together."""


class OscMap:
    """Resolves an incoming address to channel indices or a control operation."""

    def __init__(self, pairs: Sequence[tuple[str, str]], channels: ChannelMap, control_prefix: str) -> None:
        self.channels = channels
        self.dispatcher = Dispatcher(strict_timing=False)
        for pattern, template in pairs:
            capture = None
            if "*" in pattern:
                capture = re.compile("^" + "([^/]*)".join(re.escape(p) for p in pattern.split("*", 1)).replace(
                    re.escape("*"), "[^/]*") + "$")
            self.dispatcher.map(pattern, _noop, "channel", template, capture)
        for op in CONTROL_OPS:
            self.dispatcher.map(f"{control_prefix}/{op}", _noop, "control", op, None)

    def resolve(self, address: str) -> tuple[list[int], str | None]:
        """(channel indices, control op or None) the address reaches; ([], None) when it reaches nothing.
        :class:`KeyError` naming the channel when a wildcard maps to a channel the head does not have."""
        indices: list[int] = []
        control = None
        for handler in self.dispatcher.handlers_for_address(address):
            kind, value, capture = handler.args
            if kind == "control":
                control = value
                continue
            name = value
            if capture is not None:
                m = capture.match(address)
                if m is None:
                    continue
                name = value.replace("*", m.group(1), 1)
            try:
                indices.append(self.channels.index_of(name))
            except UnknownChannel:
                raise KeyError(name) from None
        return indices, control
