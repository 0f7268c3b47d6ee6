"""Atomic writes: a failed write leaves the previous file whole and no temp file behind."""

from __future__ import annotations

from pathlib import Path

import pytest

from models.atomic import atomic_path, write_bytes, write_text


def test_write_replaces_and_leaves_no_temp(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "report.json"
    write_text(target, "one\n")
    write_bytes(target, b"two\n")
    assert target.read_text() == "two\n"
    assert sorted(p.name for p in target.parent.iterdir()) == ["report.json"]
    assert target.stat().st_mode & 0o044  # readable by others, unlike a bare mkstemp file


def test_failure_keeps_the_old_file(tmp_path: Path) -> None:
    target = tmp_path / "mesh.vtu"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="writer crashed"), atomic_path(target, suffix=".vtu") as tmp:
        assert tmp.suffix == ".vtu" and tmp.parent == tmp_path
        tmp.write_text("half a fi")
        raise RuntimeError("writer crashed")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.vtu"]
