"""``tests._wait.wait_until``: returns the first truthy value, or fails naming what it awaited and the last value."""

from __future__ import annotations

import pytest

from tests._wait import wait_until


def test_returns_the_first_truthy_value() -> None:
    values = iter([0, None, [], {"state": "ready"}])
    assert wait_until(lambda: next(values), 5.0, interval=0.0) == {"state": "ready"}


def test_fails_naming_what_was_awaited_and_the_last_value() -> None:
    with pytest.raises(AssertionError, match=r"waited 0.05 s for the drive to be ready; last value: ''"):
        wait_until(lambda: "", 0.05, "the drive to be ready")
    with pytest.raises(AssertionError, match=r"last value: 0"):
        wait_until(lambda: 0, 0.05, "zero to turn truthy")


def test_a_callable_description_is_asked_at_the_timeout_and_the_default_is_the_source_line() -> None:
    state = {"n": 0}

    def count() -> int:
        state["n"] += 1
        return 0

    with pytest.raises(AssertionError, match=r"after (\d+) polls") as err:
        wait_until(count, 0.05, lambda: f"nothing, after {state['n']} polls", interval=0.01)
    assert int(err.value.args[0].split("after ")[1].split(" polls")[0]) >= 2
    with pytest.raises(AssertionError, match=r"for `wait_until\(lambda: False, 0.01\)` \(test_wait.py:\d+\)"):
        wait_until(lambda: False, 0.01)
