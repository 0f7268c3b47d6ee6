"""The house stays readable: the figures docs/architecture.md promises, measured from the source each run."""

from __future__ import annotations

import pytest

from tools.house_metrics import Figures, measure


@pytest.fixture(scope="module")
def figures() -> Figures:
    return measure()


def test_no_any_on_the_stream_frames_path(figures: Figures) -> None:
    assert figures.any_frame_path == 0


def test_runtime_modules_and_functions_stay_small(figures: Figures) -> None:
    assert not figures.runtime_over_500, figures.runtime_over_500
    assert not figures.long_functions, figures.long_functions


def test_every_command_module_follows_the_one_pattern(figures: Figures) -> None:
    assert figures.cli_modules and not figures.cli_off_pattern, figures.cli_off_pattern


def test_no_import_cycles_and_no_contract_exceptions(figures: Figures) -> None:
    assert not figures.cycles, figures.cycles
    assert figures.contract_exceptions == 0


def test_the_measures_see_what_they_count() -> None:
    import ast

    from tools.house_metrics import _follows_pattern, count_any, import_cycles

    tree = ast.parse("def f(a: Any, b: int, *c: Any) -> dict[str, Any]: ...\nx: list[Any] = []\ny: int = 0\n")
    assert count_any(tree) == 4
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _follows_pattern("runtime/cli/daemon.py") and not _follows_pattern("offline/fem_cli.py")
