"""Waiting in tests: poll a condition until it holds, or fail naming what was awaited and the last value seen.

Tests wait on the condition they need (an event, a state, a page update), never on elapsed time. The timeout only
bounds a wait that would otherwise hang on a broken build, so it is generous: a loaded two-core host stalls
processes for seconds at a time, and a passing test never waits it out.
"""

from __future__ import annotations

import linecache
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def wait_until(predicate: Callable[[], T], timeout: float, what: str | Callable[[], str] = "",
               interval: float = 0.02) -> T:
    """Poll ``predicate`` every ``interval`` s until it returns something truthy, and return that.

    After ``timeout`` s raise ``AssertionError`` naming ``what`` (by default the source line of ``predicate``; a
    callable is asked at the timeout, to describe the state the test saw) and the last value ``predicate`` returned.
    """
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > end:
            said = what() if callable(what) else what
            raise AssertionError(f"waited {timeout:g} s for {said or _source(predicate)}; last value: {value!r}")
        time.sleep(interval)


def _source(predicate: Callable[[], object]) -> str:
    """The line that defines ``predicate`` (a lambda's whole expression, usually), for a failure message."""
    code = getattr(predicate, "__code__", None)
    if code is None:
        return repr(predicate)
    line = linecache.getline(code.co_filename, code.co_firstlineno).strip()
    return f"`{line}` ({code.co_filename.rsplit('/', 1)[-1]}:{code.co_firstlineno})" if line else repr(predicate)
