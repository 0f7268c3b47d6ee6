"""Each motor bus in a process of its own, reached from the control loop without blocking.

:class:`BusProxy` is the loop side of one bus process: it posts targets and takes :class:`BusFeedback` through shared
memory in microseconds, and carries lifecycle requests over a control pipe. The bus process
(:mod:`runtime.bus.process`) runs the bus's real driver with a :class:`BusProcessConfig`, and reopens a lost
connection in the background. Modules: ``proxy`` (loop side), ``process`` (the bus process), ``layout`` (the shared
block), ``messages`` (the control pipe), ``config``.
"""

from runtime.bus.config import BusProcessConfig
from runtime.bus.proxy import BusFeedback, BusProxy

__all__ = ["BusFeedback", "BusProcessConfig", "BusProxy"]
