"""The package layering of docs/architecture.md, as import-linter contracts in pyproject.toml."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_contracts_cover_the_documented_layers() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    pairs = {(src, bad) for c in config["contracts"] for src in c["source_modules"] for bad in c["forbidden_modules"]}
    for need in [("models", "runtime"), ("models", "offline"), ("models", "drivers"), ("sim_hardware", "runtime"),
                 ("sim_hardware", "offline"), ("sim_hardware", "models.client"), ("runtime", "offline"),
                 ("runtime", "torch"), ("runtime", "sim_hardware"), ("offline", "runtime"), ("offline", "sim_hardware"),
                 ("drivers", "models"), ("drivers", "runtime"), ("likeness.cli", "runtime"),
                 ("studio", "torch"), ("studio", "runtime"), ("studio", "offline"), ("studio", "drivers")]:
        assert need in pairs, need
    assert not [c["name"] for c in config["contracts"] if c.get("ignore_imports")]  # no listed exceptions


def test_import_contracts_are_kept(capsys: pytest.CaptureFixture[str]) -> None:
    from importlinter.cli import lint_imports

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        status = lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True)
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    assert status == 0, out[out.find("Broken contracts"):] or out
