"""The read stage: every bus's latest feedback (a snapshot the runner took without blocking) taken into the core.

:class:`BusesState` keeps the measured positions and, per bus, when its devices last reported, its lifecycle state,
connection and device faults; :func:`read` takes a cycle's feedback in and :func:`announce_connections` publishes
connection changes.
The lifecycle's supervision judges this feedback (:func:`runtime.core.lifecycle.supervise`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from runtime.core.cycle import BusInput, CycleOutputs
from runtime.core.events import Body, BusConnectionChanged
from runtime.core.params import CoreParams


@dataclass(frozen=True)
class ConnectionInfo:
    """A bus's connection as telemetry reports it: state, reconnect attempts, seconds to the next (None: none due)."""

    state: str
    attempts: int
    retry_in_s: float | None

    def as_dict(self) -> Body:
        """The ``connection`` entry of telemetry."""
        return {"state": self.state, "attempts": self.attempts, "retry_in_s": self.retry_in_s}


@dataclass
class BusesState:
    """The latest feedback: measured positions (SI, NaN before any); per bus when its devices last reported (the
    oldest of their newest samples, monotonic; -inf before any), its state, connection, device faults, connection
    details and the connection state already announced."""

    measured: np.ndarray
    reported: dict[str, float]
    states: dict[str, str]
    connected: dict[str, bool]
    faults: dict[str, dict[str, tuple[int, str]]]
    connections: dict[str, ConnectionInfo] = field(default_factory=dict)
    announced: dict[str, str] = field(default_factory=dict)
    written: np.ndarray | None = None  # the buses' last written targets (SI, NaN where not known)

    @classmethod
    def initial(cls, params: CoreParams) -> BusesState:
        """Nothing measured yet; every bus unconfigured and not connected."""
        n = len(params.names)
        return cls(measured=np.full(n, np.nan), reported={b: -np.inf for b, _ in params.buses},
                   states={b: "unconfigured" for b, _ in params.buses},
                   connected={b: False for b, _ in params.buses}, faults={b: {} for b, _ in params.buses})

    def fault_table(self) -> dict[str, list[int | str]]:
        """Every device fault now, as ``"bus/device" → [code, message]``."""
        return {f"{b}/{d}": [c, m] for b, fs in self.faults.items() for d, (c, m) in fs.items()}

    def fault_detail(self, bus: str) -> str:
        """What is wrong with ``bus``: its device faults, else its state."""
        faults = self.faults[bus]
        return "; ".join(f"{d}: 0x{c:04X} {m}" for d, (c, m) in faults.items()) or f"bus state {self.states[bus]}"


def read(fb: BusesState, params: CoreParams, buses: tuple[BusInput, ...], t: float) -> None:
    """Take each bus's feedback in (``buses`` in the order of ``params.buses``)."""
    if fb.written is None:
        fb.written = np.full(len(fb.measured), np.nan)
    for (name, idx), bus in zip(params.buses, buses, strict=True):
        fb.measured[idx] = bus.positions
        fb.written[idx] = np.nan if bus.written is None else bus.written
        fb.reported[name] = bus.stamp
        fb.states[name] = bus.state
        fb.connected[name] = bus.connected
        fb.faults[name] = bus.faults
        connection = bus.connection or ("connected" if bus.connected else "closed")
        retry_in = max(0.0, bus.retry_at - t) if bus.retry_at < 1e300 else None
        info = fb.connections.get(name)
        if info is None or (info.state, info.attempts, info.retry_in_s) != (connection, bus.attempts, retry_in):
            fb.connections[name] = ConnectionInfo(connection, bus.attempts, retry_in)  # else the same one again


def announce_connections(fb: BusesState, out: CycleOutputs, t: float) -> None:
    """A ``bus_link`` event whenever a bus's connection state changes (lost, reconnecting, connected)."""
    for name, info in fb.connections.items():
        previous = fb.announced.get(name)
        if info.state != previous:
            fb.announced[name] = info.state
            if previous is not None and previous != "closed":
                out.emit(BusConnectionChanged(t, name, info.state, previous, info.attempts, info.retry_in_s))
