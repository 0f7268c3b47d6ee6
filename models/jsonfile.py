"""Reading UTF-8 text and JSON files with one-line errors that name the file, the position and what was expected.

Binary files, broken JSON and pathologically nested documents (which would overflow the recursion of
:func:`json.loads`) all become a :class:`~models.errors.SpecError` instead of a traceback.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from models.errors import SpecError

#: Deepest nesting of arrays and objects accepted in a JSON file (asset formats need fewer than 10 levels).
MAX_DEPTH = 64

_TOKENS = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]', re.DOTALL)


def read_text(path: str | Path, what: str = "file") -> str:
    """The file's text; SpecError for an unreadable file or one that is not UTF-8 (naming the byte offset)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SpecError(str(path), "file", f"cannot read {what}: {exc.strerror or exc}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise SpecError(str(path), f"byte {exc.start} (line {line})",
                        f"expected UTF-8 text for a {what}, found byte 0x{data[exc.start]:02x}") from None


def nesting_problem(text: str, max_depth: int = MAX_DEPTH) -> tuple[int, int] | None:
    """(line, column) where arrays/objects in JSON ``text`` nest deeper than ``max_depth``; None when they do not."""
    depth = 0
    for m in _TOKENS.finditer(text):
        tok = m.group()
        if tok in "[{":
            depth += 1
            if depth > max_depth:
                line = text.count("\n", 0, m.start()) + 1
                return line, m.start() - (text.rfind("\n", 0, m.start()) + 1) + 1
        elif tok in "]}":
            depth -= 1
    return None


def parse_json(text: str, source: str, what: str = "file", max_depth: int = MAX_DEPTH) -> Any:
    """Parse JSON ``text`` read from ``source``; SpecError naming line and column of a syntax or nesting error."""
    deep = nesting_problem(text, max_depth)
    if deep is not None:
        raise SpecError(source, f"line {deep[0]} column {deep[1]}",
                        f"expected a {what} nested at most {max_depth} levels deep")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise SpecError(source, f"line {exc.lineno} column {exc.colno}",
                        f"not valid JSON for a {what}: {exc.msg}") from None
    except RecursionError:  # defensive: the depth check above should have caught it
        raise SpecError(source, "json", f"expected a {what} nested at most {max_depth} levels deep") from None


def load_json(path: str | Path, what: str = "file", max_depth: int = MAX_DEPTH) -> Any:
    """Read and parse a UTF-8 JSON file; every problem is a one-line SpecError naming the file and position."""
    return parse_json(read_text(path, what), str(path), what, max_depth)
