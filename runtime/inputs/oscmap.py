"""OSC addresses → channels (``[inputs.osc.map]``) and control addresses, matched by python-osc's dispatcher.

``"/face/jaw" = "jaw"`` maps one address; ``"/face/arkit/*" = "arkit.*"`` maps every address under ``/face/arkit/``
to the channel named by what the ``*`` stands for (``/face/arkit/jawOpen`` → ``arkit.jawOpen``): such an entry is
expanded once into one address per channel of the head it can name. Incoming address patterns
(``/face/brow/{l,r}``, ``/face/*``) then reach every mapped address they match, as OSC specifies.
"""

from __future__ import annotations

from collections.abc import Sequence

from pythonosc.dispatcher import Dispatcher

from runtime.core.channels import ChannelMap

CONTROL_OPS = ("enable", "disable", "play", "stop", "estop")


def _noop(*_: object) -> None:
    """Handlers are looked up, never invoked: the input applies a packet's messages together."""


def expand(pairs: Sequence[tuple[str, str]], names: Sequence[str]) -> list[tuple[str, str]]:
    """Concrete (address, channel) pairs: an entry with a ``*`` gives one pair per channel its pattern names."""
    out = []
    for address, channel in pairs:
        if "*" not in channel:
            out.append((address, channel))
            continue
        prefix, _, suffix = channel.partition("*")
        for name in names:
            if name.startswith(prefix) and name.endswith(suffix) and len(name) > len(prefix) + len(suffix):
                part = name[len(prefix):len(name) - len(suffix)]
                if "/" not in part:
                    out.append((address.replace("*", part, 1), name))
    return out


class OscMap:
    """Resolves an incoming address (or address pattern) to channel indices or a control operation."""

    def __init__(self, pairs: Sequence[tuple[str, str]], channels: ChannelMap, control_prefix: str) -> None:
        self.dispatcher = Dispatcher(strict_timing=False)
        for address, channel in expand(pairs, channels.names):
            self.dispatcher.map(address, _noop, "channel", channels.index_of(channel))
        for op in CONTROL_OPS:
            self.dispatcher.map(f"{control_prefix}/{op}", _noop, "control", op)

    def resolve(self, address: str) -> tuple[list[int], str | None]:
        """(channel indices, control op or None) the address reaches; ([], None) when it reaches nothing."""
        indices: list[int] = []
        control = None
        for handler in self.dispatcher.handlers_for_address(address):
            kind, value = handler.args
            if kind == "control":
                control = value
            else:
                indices.append(value)
        return indices, control
