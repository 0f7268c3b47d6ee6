"""The ``likeness`` command's one registry: help lists every command without importing any command module, each
command module has the one shape and imports only the standard library, and errors map to one line and a status."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from likeness.cli import COMMANDS, GROUPS, TOP, find_command, main

ROOT = Path(__file__).resolve().parents[1]
PROJECT = ("runtime", "offline", "sim_hardware", "studio", "models", "drivers")


def _imported(*argv: str) -> tuple[str, set[str]]:
    """Run ``python -X importtime -m likeness ARGV``: its stdout and the modules it imported."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-X", "importtime", "-m", "likeness", *argv], capture_output=True,
                         text=True, env=env, cwd=ROOT, timeout=60)
    assert res.returncode == 0, res.stderr[-2000:]
    modules = {line.rsplit("|", 1)[-1].strip() for line in res.stderr.splitlines() if line.startswith("import time:")}
    return res.stdout, modules


@pytest.mark.parametrize("argv", [("--help",), ("offline", "--help"), ("sim", "--help")])
def test_help_lists_commands_without_importing_them_or_numpy(argv: tuple[str, ...]) -> None:
    out, modules = _imported(*argv)
    group = argv[0] if argv[0] in GROUPS else TOP
    for cmd in COMMANDS:
        if cmd.group == group:
            assert f" {cmd.name} " in out or f" {cmd.name}\n" in out, cmd.name
    assert "numpy" not in modules
    assert not {m for m in modules if m.split(".")[0] in PROJECT}, sorted(m for m in modules if m.split(".")[0]
                                                                          in PROJECT)


def test_every_command_module_has_the_one_shape_and_imports_only_the_standard_library() -> None:
    code = ("import importlib, sys\nfrom likeness.cli import COMMANDS\n"
            "mods = [importlib.import_module(c.module) for c in COMMANDS]\n"
            "assert all(callable(m.add_arguments) and callable(m.run) for m in mods)\n"
            "print(' '.join(sorted(sys.modules)))")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=60)
    assert res.returncode == 0, res.stderr[-2000:]
    loaded = set(res.stdout.split())
    heavy = {m for m in loaded if m.split(".")[0] in ("numpy", "scipy", "torch", "zmq", "msgpack", "models", "drivers")}
    assert not heavy, sorted(heavy)
    outside = {m for m in loaded if m.split(".")[0] in PROJECT and ".cli" not in m and "." in m}
    assert not outside, sorted(outside)


def test_every_command_module_is_registered_once() -> None:
    names = [(c.group, c.name) for c in COMMANDS]
    assert len(set(names)) == len(names)
    files = {f"{p.parent.parent.name}.cli.{p.stem}" for pillar in ("runtime", "offline", "sim_hardware", "studio")
             for p in (ROOT / pillar / "cli").glob("*.py") if not p.stem.startswith("_")}
    assert files <= {c.module for c in COMMANDS}, files - {c.module for c in COMMANDS}


def test_each_command_builds_its_options() -> None:
    for cmd in COMMANDS:
        argv = [cmd.name] if cmd.group == TOP else [cmd.group, cmd.name]
        assert find_command([*argv, "--help"]) == cmd
        assert find_command(["-v", *argv, "--x", "1"]) == cmd
        with pytest.raises(SystemExit) as exit_info:
            main([*argv, "--help"])
        assert exit_info.value.code == 0
        importlib.import_module(cmd.module)


def test_no_command_or_group_without_tool_prints_help_and_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out
    assert main(["offline"]) == 2
    assert "TOOL" in capsys.readouterr().out
    assert main(["sim"]) == 2
    assert "DEVICE" in capsys.readouterr().out


def test_a_usage_error_is_one_line_with_status_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["stream", str(tmp_path / "clip.json"), "--fps", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["likeness stream: error: --fps and --speed must be positive"]
    assert main(["offline", "dataset", "--config", str(ROOT / "heads" / "sample" / "head.toml"), "--poses", "0",
                 "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["likeness offline: error: --poses must be positive, got 0"]


def test_import_free_copies_of_library_constants_agree() -> None:
    import offline.cli._common
    import runtime.cli.recording
    from models.material import MATERIAL_MODELS
    from runtime.recording import REPLAY_MAX_KEYS

    assert runtime.cli.recording.REPLAY_MAX_KEYS == REPLAY_MAX_KEYS
    assert set(offline.cli._common.MATERIAL_MODELS) == set(MATERIAL_MODELS)
