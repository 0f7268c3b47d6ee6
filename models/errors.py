"""Errors raised when a file crossing the offline/runtime boundary is invalid."""

from __future__ import annotations

from typing import Any

_MISSING = object()


class SpecError(ValueError):
    """An invalid head spec, link map, predictor or data file; names the file, key and bad value."""

    def __init__(self, source: str, key: str, message: str, value: Any = _MISSING) -> None:
        text = f"{source}: {key}: {message}"
        if value is not _MISSING:
            text += f" (got {value!r})"
        super().__init__(text)
        self.source = source
        self.key = key
