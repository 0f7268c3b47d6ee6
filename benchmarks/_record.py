"""A benchmark's printed report, kept as it is printed, and written to a file atomically under its header."""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def captured() -> Iterator[io.StringIO]:
    """Print as usual while keeping a copy of everything printed (the yielded buffer)."""
    out = io.StringIO()

    class Tee(io.TextIOBase):
        def write(self, text: str) -> int:
            sys.__stdout__.write(text)
            return out.write(text)

    with contextlib.redirect_stdout(Tee()):
        yield out


def write_report(path: Path, header: str, body: str) -> None:
    """Write ``header`` then ``body`` to ``path`` through a temporary file, so a reader never sees half a report."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(header + body, encoding="utf-8")
    tmp.replace(path)
