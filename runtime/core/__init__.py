"""The control core: ``step(state, params, inputs) -> outputs`` (:mod:`runtime.core.core`), and its public entry
points for the loop runner."""

from runtime.core.core import _fault

#: Enter FAULT from outside a cycle's stages (the runner, when a cycle raised): same signature as the core's own.
fault = _fault
