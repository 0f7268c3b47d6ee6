"""A head file with show-control inputs added: the head's own file plus an ``[inputs]`` fragment, written anew.

``likeness daemon --inputs FRAGMENT.toml`` (and the tests and examples) run a head with the inputs of a fragment
file that holds only ``[inputs.*]`` tables, without editing the head file. Relative file references of the head
(``[paths]``, ``[skin_material] fit``) are made absolute so the combined file may live anywhere.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from models.errors import SpecError

_FILE_REF = re.compile(r'^(\s*\w+\s*=\s*")([^"/][^"]*\.(?:onnx|json|npz|toml|csv))(")', re.MULTILINE)


def head_with_inputs(head: Path, fragment: Path, out: Path) -> Path:
    """Write ``out``: ``head`` with its file references absolute, then the ``[inputs]`` tables of ``fragment``."""
    head, fragment = Path(head).resolve(), Path(fragment)
    text = head.read_text(encoding="utf-8")
    extra = fragment.read_text(encoding="utf-8")
    try:
        data = tomllib.loads(extra)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(str(fragment), "toml", f"not valid TOML: {exc}") from None
    if set(data) != {"inputs"}:
        raise SpecError(str(fragment), ", ".join(sorted(set(data) - {"inputs"})) or "(file)",
                        "an inputs fragment holds only [inputs.*] tables")
    if "inputs" in tomllib.loads(text):
        raise SpecError(str(head), "inputs", "the head already has [inputs]; edit it there")

    def absolute(m: re.Match[str]) -> str:
        p = head.parent / m.group(2)
        return f"{m.group(1)}{p.as_posix() if p.exists() else m.group(2)}{m.group(3)}"

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(_FILE_REF.sub(absolute, text) + f"\n# ---- inputs from {fragment.name}\n" + extra, encoding="utf-8")
    return out
