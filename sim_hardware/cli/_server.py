"""What the ``likeness sim`` device servers share (standard library only): per-device start positions and parent
supervision."""

from __future__ import annotations

import os


def parse_counts(text: str) -> dict[int, float]:
    """``"1=120,2=-4096.5"`` → ``{1: 120.0, 2: -4096.5}`` (ValueError naming the bad part)."""
    out: dict[int, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = part.partition("=")
        try:
            if not sep:
                raise ValueError
            out[int(key)] = float(value)
        except ValueError:
            raise ValueError(f"cannot parse {part!r} (use ID=COUNTS, e.g. 1=120,2=-4096)") from None
    return out


class ParentWatch:
    """Tells whether the process that started this one is gone (re-parented), so a server can exit with it."""

    def __init__(self, enabled: bool) -> None:
        self._parent = os.getppid() if enabled else None

    def parent_gone(self) -> bool:
        """True once the starting process has exited (always False when not watching)."""
        return self._parent is not None and os.getppid() != self._parent
