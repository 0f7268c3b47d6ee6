"""Find racing tests: run the default suite several times, each a fresh pytest process, and compare the outcomes.

Each run writes a JUnit XML file; the report lists the runs (exit status, tests, failures, wall time), the tests that
failed in some runs and passed in others (flaky) with their failure messages, and the tests that failed in every run
they ran in. The exit status is 0 only if every run passed.

    python -m tools.flaky --runs 10                        # the default suite (pyproject's addopts), ten times
    python -m tools.flaky --runs 3 -- tests/drivers -x     # arguments after -- go to pytest
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PASSED, FAILED, SKIPPED = "passed", "failed", "skipped"


@dataclass(frozen=True)
class Outcome:
    """One test's result in one run, with the first line of its failure message when it failed."""

    status: str
    message: str = ""


@dataclass
class Run:
    """One pytest process: its exit status, wall time and every test's outcome (by node id)."""

    index: int
    returncode: int
    wall_s: float
    outcomes: dict[str, Outcome] = field(default_factory=dict)


def parse_junit(path: Path) -> dict[str, Outcome]:
    """Outcomes by test id (``classname::name``: the module's dotted path, a class if any, and the test's name) from a
    JUnit XML file."""
    outcomes: dict[str, Outcome] = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        classname = case.get("classname", "")
        name = case.get("name", "")
        test_id = f"{classname}::{name}" if classname else name
        bad = case.find("failure")
        if bad is None:
            bad = case.find("error")
        if bad is not None:
            message = (bad.get("message") or (bad.text or "").strip() or bad.tag).strip().splitlines()
            outcomes[test_id] = Outcome(FAILED, message[0] if message else bad.tag)
        elif case.find("skipped") is not None:
            outcomes.setdefault(test_id, Outcome(SKIPPED))
        else:
            outcomes.setdefault(test_id, Outcome(PASSED))
    return outcomes


def classify(runs: Sequence[Run]) -> tuple[dict[str, list[tuple[int, str]]], dict[str, str]]:
    """Flaky tests (failed in some runs, passed in others: each failing run and its message) and tests that always
    failed (their last message)."""
    flaky: dict[str, list[tuple[int, str]]] = {}
    always: dict[str, str] = {}
    names = sorted({name for run in runs for name in run.outcomes})
    for name in names:
        seen = [(run.index, run.outcomes[name]) for run in runs if name in run.outcomes]
        failures = [(i, o.message) for i, o in seen if o.status == FAILED]
        if not failures:
            continue
        if any(o.status == PASSED for _, o in seen):
            flaky[name] = failures
        else:
            always[name] = failures[-1][1]
    return flaky, always


def render(runs: Sequence[Run]) -> str:
    """The report as plain text."""
    flaky, always = classify(runs)
    lines = [f"{len(runs)} run(s)"]
    for run in runs:
        failed = sum(o.status == FAILED for o in run.outcomes.values())
        lines.append(f"  run {run.index}: exit {run.returncode}, {len(run.outcomes)} tests, {failed} failed, "
                     f"{run.wall_s:.0f} s")
    lines.append(f"flaky (failed in some runs, passed in others): {len(flaky)}")
    for name, failures in flaky.items():
        lines.append(f"  {name}: failed in run(s) {', '.join(str(i) for i, _ in failures)}")
        lines.extend(f"    run {i}: {message}" for i, message in failures)
    lines.append(f"always failed: {len(always)}")
    lines.extend(f"  {name}: {message}" for name, message in always.items())
    return "\n".join(lines)


def run_suite(index: int, out_dir: Path, pytest_args: Sequence[str]) -> Run:
    """One fresh pytest process writing ``run-<index>.xml`` and ``run-<index>.log`` under ``out_dir``."""
    xml = out_dir / f"run-{index}.xml"
    log = out_dir / f"run-{index}.log"
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={xml}", *pytest_args]
    start = time.monotonic()
    with log.open("w") as out:
        returncode = subprocess.run(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, check=False).returncode
    wall = time.monotonic() - start
    return Run(index, returncode, wall, parse_junit(xml) if xml.is_file() else {})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="how many times to run the suite (default 10)")
    parser.add_argument("--out", type=Path, default=ROOT / "build" / "flaky",
                        help="folder for each run's JUnit XML and log, and report.txt (default build/flaky)")
    parser.add_argument("pytest_args", nargs="*", help="arguments for pytest (after --)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for index in range(1, args.runs + 1):
        run = run_suite(index, args.out, args.pytest_args)
        print(f"run {index}/{args.runs}: exit {run.returncode}, {run.wall_s:.0f} s", flush=True)
        runs.append(run)
    report = render(runs)
    (args.out / "report.txt").write_text(report + "\n")
    print(report)
    return 0 if all(run.returncode == 0 for run in runs) else 1


if __name__ == "__main__":
    raise SystemExit(main())
