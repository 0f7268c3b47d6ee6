"""The in-cycle kernels compiled ahead of time into an extension module, so the control loop runs them without numba.

Importing numba (its compiler, LLVM) costs a process about 110 MiB of resident memory, and loading the kernels from
numba's own on-disk cache another 70 MiB (the code generator stays resident): most of a resting daemon's memory, for
seven small functions. :func:`build` compiles the functions the loop calls (:data:`EXPORTS`, from :data:`SOURCES`)
with numba's ahead-of-time compiler (``numba.pycc``) into an ordinary extension module (about 1 MiB, for the host CPU
as the JIT compiles) under ``models/__pycache__/``, typed with the argument types a head's solver, strain guard and
clips pass (numba's own typing of real arguments, so the compiled code is the code the JIT would run).
:func:`kernel` returns that module's function when it is built for these sources, library versions and CPU, else the
JIT function (numba imported on first use, as before). ``python -m models.kernels`` (``make install``) builds it.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.machinery
import importlib.metadata
import importlib.util
import logging
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: The kernels the control loop calls (the rest of :data:`SOURCES` is reached through them).
EXPORTS = ("solve_values_measured", "reduced_measure", "solve_frame", "solve_frame_measured", "guard_limit",
           "guard_step", "bezier_sample", "following_watch", "channel_targets")
#: The modules that define them (numba JIT functions), in :data:`EXPORTS`' order of first use.
SOURCES = ("_skin_kernels", "_cycle_kernels")
#: Modules whose functions they compile besides (a clip's Bezier evaluation): their sources are part of :func:`key`.
COMPILED_FROM = ("clip",)
MODULE = "_skin_kernels_aot"
_HERE = Path(__file__).resolve().parent


def key() -> str:
    """What the built module must match: the kernels' source, the exported names, numba's, numpy's and Python's
    versions."""
    h = hashlib.sha256()
    for source in SOURCES + COMPILED_FROM:
        h.update((_HERE / f"{source}.py").read_bytes())
    h.update(" ".join(EXPORTS).encode())
    try:
        numba_version = importlib.metadata.version("numba")
    except importlib.metadata.PackageNotFoundError:
        numba_version = "none"
    h.update(f"{numba_version} {np.__version__} {sys.version} {sys.platform} {_cpu()}".encode())
    return h.hexdigest()[:16]


@functools.cache
def _cpu() -> str:
    """This CPU's model and instruction-set flags (the module is compiled for the host CPU, as numba's JIT is)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        import platform

        return platform.processor() or platform.machine()
    first = text.split("\n\n", 1)[0]
    keep = [line for line in first.splitlines() if line.split(":")[0].strip() in ("model name", "flags")]
    return " ".join(keep)


def build_dir() -> Path:
    """Where the module for the current :func:`key` lives (``LIKENESS_KERNEL_DIR`` overrides the parent)."""
    root = Path(os.environ.get("LIKENESS_KERNEL_DIR", _HERE / "__pycache__"))
    return root / f"skin_kernels_aot-{key()}"


@functools.cache
def module() -> ModuleType | None:
    """The ahead-of-time module built for the current sources and versions, loaded (numba is not imported); None
    when it is not built."""
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    path = build_dir() / f"{MODULE}{suffix}"
    if not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location(MODULE, path)
    if spec is None or spec.loader is None:
        return None
    try:
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    except ImportError as exc:  # a build for another interpreter or platform
        log.warning("in-cycle kernels built ahead of time at %s cannot load (%s): using numba's JIT", path, exc)
        return None
    if not all(hasattr(mod, name) for name in EXPORTS):
        return None
    return mod


def kernel(name: str) -> Callable[..., Any]:
    """The kernel ``name`` of :data:`EXPORTS`: the ahead-of-time one when built, else numba's JIT (imports numba).
    A call with argument types the ahead-of-time build was not typed for falls back to the JIT for that call."""
    if name not in EXPORTS:
        raise KeyError(f"{name!r} is not an exported kernel; exported: {', '.join(EXPORTS)}")
    if _RECORDING:
        return _recorder(name, jit(name), list(_RECORDING))
    mod = module()
    if mod is None:
        return jit(name)
    fn = _AOT.get(name)
    if fn is None:
        fn = _AOT[name] = _with_fallback(name, getattr(mod, name))
    return fn


_AOT: dict[str, Callable[..., Any]] = {}


@functools.cache
def jit(name: str) -> Callable[..., Any]:
    """The numba JIT function ``name`` from whichever of :data:`SOURCES` defines it (imports numba)."""
    import importlib

    for source in SOURCES:
        fn = getattr(importlib.import_module(f"models.{source}"), name, None)
        if fn is not None:
            return fn
    raise KeyError(f"no kernel module defines {name!r}")


def _with_fallback(name: str, aot: Callable[..., Any]) -> Callable[..., Any]:
    warned = False

    def call(*args: Any) -> Any:
        nonlocal warned
        try:
            return aot(*args)
        except TypeError:  # argument types outside the ahead-of-time signature
            if not warned:  # once: the caller may be the control loop
                warned = True
                log.warning("kernel %s: arguments %s not in its ahead-of-time build; using numba's JIT", name,
                            [getattr(a, "dtype", type(a).__name__) for a in args])
            return jit(name)(*args)

    call.__name__ = name
    call.__doc__ = f"{name} of the in-cycle kernels, compiled ahead of time (numba's JIT as a fallback)."
    return call


def recording(examples: dict[str, tuple[Any, ...]]) -> Any:
    """A context manager: while it is open, :func:`kernel` hands out the JIT kernels wrapped so that the first call
    of each puts its arguments in ``examples`` (the arguments :func:`build` types the module by)."""
    import contextlib

    @contextlib.contextmanager
    def record() -> Any:
        _RECORDING.append(examples)
        try:
            yield examples
        finally:
            _RECORDING.remove(examples)

    return record()


_RECORDING: list[dict[str, tuple[Any, ...]]] = []


def _recorder(name: str, fn: Callable[..., Any], into: list[dict[str, tuple[Any, ...]]]) -> Callable[..., Any]:
    def call(*args: Any) -> Any:
        for examples in into:
            examples.setdefault(name, args)
        return fn(*args)

    return call


def build(examples: Mapping[str, Sequence[Any]]) -> Path:
    """Compile :data:`EXPORTS` ahead of time, each typed by numba from its example arguments in ``examples`` (the
    arguments a head's solver and guard pass), into :func:`build_dir`; returns the module's path. Written to a
    temporary directory first and moved into place whole."""
    from numba import typeof
    from numba.pycc import CC

    missing = [name for name in EXPORTS if name not in examples]
    if missing:
        raise ValueError(f"no example arguments for {', '.join(missing)}")
    target = build_dir()
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=target.parent))
    try:
        from llvmlite import binding

        cc = CC(MODULE)
        cc.target_cpu = binding.get_host_cpu_name()  # as the JIT compiles (the key names this CPU)
        cc.output_dir = str(tmp)
        cc.verbose = False
        for name in EXPORTS:
            dispatcher = jit(name)
            args = tuple(examples[name])
            dispatcher(*args)  # compiled by the JIT first: its typing gives the return type
            argtypes = tuple(typeof(a) for a in args)
            if argtypes not in dispatcher.overloads:
                raise RuntimeError(f"kernel {name}: no JIT overload for {argtypes}")
            cc.export(name, dispatcher.overloads[argtypes].signature)(dispatcher.py_func)
        cc.compile()
        if target.exists():
            shutil.rmtree(target)
        os.replace(tmp, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    module.cache_clear()
    _AOT.clear()
    return target / f"{MODULE}{importlib.machinery.EXTENSION_SUFFIXES[0]}"
