"""``tools.flaky``'s reading of JUnit files and its verdicts, on small synthetic runs (the suite is never run here)."""

from __future__ import annotations

from pathlib import Path

from tools.flaky import FAILED, PASSED, SKIPPED, Outcome, Run, classify, parse_junit, render

JUNIT = """<?xml version="1.0" encoding="utf-8"?>
<testsuites><testsuite name="pytest" errors="1" failures="1" skipped="1" tests="5">
<testcase classname="tests.drivers.test_bus" name="test_ok" time="0.1"/>
<testcase classname="tests.drivers.test_bus" name="test_close[virtual]" time="2.0">
  <failure message="AssertionError: waited 10 s for every drive PRE-OPERATIONAL&#10;second line">trace</failure>
</testcase>
<testcase classname="tests.studio.test_browser.TestPage" name="test_key" time="0.2">
  <skipped type="pytest.skip" message="no chromium">skip</skipped>
</testcase>
<testcase classname="tests.runtime.test_loop" name="test_setup_breaks" time="0.0">
  <error message="failed on setup with &quot;OSError: port taken&quot;">trace</error>
</testcase>
<testcase classname="tests.runtime.test_loop" name="test_teardown_breaks" time="0.0"/>
<testcase classname="tests.runtime.test_loop" name="test_teardown_breaks" time="0.0">
  <error message="failed on teardown">trace</error>
</testcase>
</testsuite></testsuites>
"""


def test_parse_junit_reads_passes_failures_errors_and_skips(tmp_path: Path) -> None:
    path = tmp_path / "run-1.xml"
    path.write_text(JUNIT)
    outcomes = parse_junit(path)
    assert outcomes == {
        "tests.drivers.test_bus::test_ok": Outcome(PASSED),
        "tests.drivers.test_bus::test_close[virtual]": Outcome(
            FAILED, "AssertionError: waited 10 s for every drive PRE-OPERATIONAL"),
        "tests.studio.test_browser.TestPage::test_key": Outcome(SKIPPED),
        "tests.runtime.test_loop::test_setup_breaks": Outcome(FAILED, 'failed on setup with "OSError: port taken"'),
        # a test that passed and then failed in teardown (two testcase entries) failed
        "tests.runtime.test_loop::test_teardown_breaks": Outcome(FAILED, "failed on teardown"),
    }


def test_classify_tells_flaky_from_always_failing_tests() -> None:
    runs = [
        Run(1, 1, 30.0, {"a": Outcome(PASSED), "b": Outcome(FAILED, "boom"), "c": Outcome(FAILED, "x1")}),
        Run(2, 1, 31.0, {"a": Outcome(FAILED, "late"), "b": Outcome(FAILED, "boom"), "c": Outcome(SKIPPED)}),
        Run(3, 0, 29.0, {"a": Outcome(PASSED), "c": Outcome(PASSED)}),
    ]
    flaky, always = classify(runs)
    assert flaky == {"a": [(2, "late")], "c": [(1, "x1")]}
    assert always == {"b": "boom"}
    text = render(runs)
    assert "3 run(s)" in text and "run 2: exit 1, 3 tests, 2 failed, 31 s" in text
    assert "a: failed in run(s) 2" in text and "run 2: late" in text
    assert "always failed: 1" in text and "b: boom" in text


def test_a_run_that_left_no_junit_file_counts_no_tests() -> None:
    runs = [Run(1, 2, 5.0), Run(2, 0, 40.0, {"a": Outcome(PASSED)})]
    assert classify(runs) == ({}, {})
    assert "run 1: exit 2, 0 tests, 0 failed, 5 s" in render(runs)
