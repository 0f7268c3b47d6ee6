"""The skin predictor checked by onnxruntime itself at daemon start, in a short-lived process of its own.

The daemon's processes read the predictor without onnxruntime (the loop runs its solve and strain guard on the
weights, the API server its full strain check in NumPy: :mod:`runtime.strain_check`), so a file whose graph parses
but that onnxruntime refuses (an unknown operator, a bad shape) would show only where something runs a full pass.
:class:`PredictorCheck` starts ``python -m runtime.predictor_check PATH`` while the daemon builds the rest (its
solvers, the guard), which opens an onnxruntime session on the file and predicts one pose; :meth:`PredictorCheck.result`
raises the :class:`~models.errors.SpecError` naming the file that the child reported (the CLI prints it as one line
and exits with status 2). The child's memory (onnxruntime alone is ~44 MB) is gone with it. A file onnxruntime
accepted is remembered by its content hash and onnxruntime's version (``$LIKENESS_CACHE``, default
``~/.cache/likeness``, ``predictor_check/``), so the next start on the same file skips the check (about a second).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from models.errors import SpecError

#: How long the check may take (a loaded two-core host imports onnxruntime in seconds).
TIMEOUT_S = 120.0
#: Exit status of the child when onnxruntime refused the file (its one-line reason on stderr).
REFUSED = 2


class PredictorCheck:
    """A running check of the predictor at ``path`` (started at construction)."""

    def __init__(self, path: Path, env: dict[str, str] | None = None) -> None:
        self.path = Path(path)
        self._marker = _marker(self.path)
        self._proc: subprocess.Popen[str] | None = None
        if self._marker is not None and self._marker.is_file():
            return  # this very file was accepted before
        self._proc = subprocess.Popen([sys.executable, "-m", "runtime.predictor_check", str(self.path)],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                      env=env if env is not None else dict(os.environ))

    @property
    def cached(self) -> bool:
        """Whether the file was accepted before (no check runs)."""
        return self._proc is None

    def result(self) -> None:
        """Wait for the check; raises :class:`SpecError` naming the file when onnxruntime refused it or the check
        itself failed."""
        if self._proc is None:
            return
        try:
            _, err = self._proc.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.cancel()
            raise SpecError(str(self.path), "graph", f"onnxruntime did not load the model within {TIMEOUT_S:g} s") \
                from None
        if self._proc.returncode == 0:
            _remember(self._marker)
            return
        lines = [line for line in (err or "").splitlines() if line.strip()]
        last = lines[-1] if lines else ""
        if self._proc.returncode == REFUSED and last:
            raise SpecError(str(self.path), "graph", last)
        raise SpecError(str(self.path), "graph", f"the onnxruntime check of the model failed (exit status "
                        f"{self._proc.returncode}): {last or 'no message'}")

    def cancel(self) -> None:
        """Stop the check (the daemon's start failed elsewhere)."""
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()


def _marker(path: Path) -> Path | None:
    """Where an accepted file is remembered: its SHA-256 and onnxruntime's version (None: no hash, no version)."""
    import hashlib
    from importlib import metadata

    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        version = metadata.version("onnxruntime")
    except (OSError, metadata.PackageNotFoundError):
        return None
    base = os.environ.get("LIKENESS_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "likeness")
    return Path(base) / "predictor_check" / f"{digest}-onnxruntime-{version}"


def _remember(marker: Path | None) -> None:
    """Remember an accepted file (no writable cache: it is checked again next time)."""
    from models.atomic import write_text

    if marker is None:
        return
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        write_text(marker, "accepted by onnxruntime\n")
    except OSError:
        pass


def check(path: Path) -> None:
    """In this process: open an onnxruntime session on the predictor and predict the middle of its range."""
    import numpy as np

    from models.predictor import SkinPredictor

    predictor = SkinPredictor(path)
    mid = 0.5 * (predictor.lo + predictor.hi)
    out = predictor.predict(np.asarray(mid, dtype=np.float64))
    if out.shape != (predictor.n_vertices, 3) or not np.all(np.isfinite(out)):
        raise SpecError(str(path), "graph", f"onnxruntime's prediction has shape {out.shape} or is not finite")


def main(argv: list[str]) -> int:
    """Entry point of the child: 0 when onnxruntime runs the model, :data:`REFUSED` with the reason on stderr."""
    if len(argv) != 1:
        print("usage: python -m runtime.predictor_check PREDICTOR.onnx", file=sys.stderr)
        return 64
    try:
        check(Path(argv[0]))
    except SpecError as exc:  # the reason alone: the daemon names the file and key
        text = str(exc)
        prefix = f"{exc.source}: {exc.key}: "
        print((text[len(prefix):] if text.startswith(prefix) else text).replace("\n", " "), file=sys.stderr)
        return REFUSED
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
