"""The control core: ``step(state, params, inputs) -> outputs`` (:mod:`runtime.core.core`) composing small systems,
each a pure step over its own part of the state (see docs/architecture.md, "The control core")."""
