"""The in-cycle frame solve against the same kernel at another revision, interleaved frame by frame in one process.

Loads ``models/_skin_kernels.py`` as it stands in the working tree and as it was at ``--against`` (``git show``),
both compiled by numba's JIT, and runs each frame of ``benchmarks/skin_solve.py`` (the sample head's blendshape
performance at 500 Hz, then random sparse frames) through both, in alternating order, each after the same cache
sweep, each on its own warm-start chain and kept Gauss-Newton matrix. On a shared or virtual machine absolute
timings drift run to run; interleaving exposes both to the same drift, so the ratio (this tree over the revision,
p1 / p50 / p99) is the figure to read. It also prints the largest pose difference between the two (rounding only,
when the change keeps the arithmetic). The revision's ``solve_values_measured`` must take the packed layout of this
tree's ``models.kernel_args.pack_frame_args``.

Run: ``python benchmarks/skin_kernel_ab.py --against REV [--config HEAD.toml] [--random 1000] [--record FILE]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import importlib.util  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.skin_solve import Paths, frames  # noqa: E402
from models.headspec import load_head  # noqa: E402

SOURCE = "models/_skin_kernels.py"
LAYOUT = "models/kernel_args.py"  # pack_frame_args: the layout both kernels must read


def _packing(source: str) -> str | None:
    """The source of ``pack_frame_args`` in a version of :data:`LAYOUT` (None when it has none)."""
    import ast

    for node in ast.parse(source).body:
        if isinstance(node, ast.FunctionDef) and node.name == "pack_frame_args":
            return ast.get_source_segment(source, node)
    return None


def _takes_carry(fn) -> bool:
    """Whether a revision's frame kernel keeps the last solution across frames (a ``carry`` argument)."""
    import inspect

    return "carry" in inspect.signature(fn.py_func).parameters


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--against", required=True, help="git revision whose kernel is the baseline (e.g. HEAD~1)")
    ap.add_argument("--config", default="heads/sample/head.toml", help="head file (default: the sample head)")
    ap.add_argument("--random", type=int, default=1000, help="random frames after the performance (default 1000)")
    ap.add_argument("--record", default=None, help="also write the report to this file")
    args = ap.parse_args(argv)
    old_src = subprocess.run(["git", "show", f"{args.against}:{SOURCE}"], cwd=ROOT, capture_output=True, text=True)
    if old_src.returncode != 0:
        print(f"cannot read {SOURCE} at {args.against}: {old_src.stderr.strip()}", file=sys.stderr)
        return 2
    old_layout = subprocess.run(["git", "show", f"{args.against}:{LAYOUT}"], cwd=ROOT, capture_output=True, text=True)
    if old_layout.returncode != 0 or _packing(old_layout.stdout) != _packing((ROOT / LAYOUT).read_text()):
        print(f"{LAYOUT} at {args.against} packs the frame's constants differently from this tree's: its kernel "
              "would misread them; compare against a revision with this tree's pack_frame_args", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="likeness-kernel-ab-") as tmp:
        old_path = Path(tmp) / "baseline_kernels.py"
        old_path.write_text(old_src.stdout)
        kernels = {"baseline": _load("baseline_kernels", old_path).solve_values_measured,
                   "this tree": _load("tree_kernels", ROOT / SOURCE).solve_values_measured}
        head = load_head(args.config if Path(args.config).is_absolute() else ROOT / args.config)
        paths = Paths(head)
        fr = frames(paths.channels, args.random)
        n = len(paths.array.names)
        reuse = {k: paths.array.inverse.frame_state(paths.array.frame.reuse.frames) for k in kernels}
        # what each kernel keeps from frame to frame: the matrix and its state, and the solution where it keeps one
        kept = {k: (lambda r, fn=fn: (r.matrix, r.state, r.carry) if _takes_carry(fn) else (r.matrix, r.state))
                for k, fn in kernels.items()}
        pose = {k: np.empty(n) for k in kernels}
        weights = {k: np.zeros(paths.array.inverse.n_units) for k in kernels}
        prev = {k: paths.array.neutral.copy() for k in kernels}
        times: dict[str, dict[str, list[float]]] = {k: {"performance": [], "random": []} for k in kernels}
        for k, fn in kernels.items():  # compile both before timing
            warm = paths.array.inverse.frame_state(paths.array.frame.reuse.frames)
            fn(fr[0][1], weights[k], prev[k].copy(), pose[k], *kept[k](warm), *paths.kernel_args)
        largest = 0.0
        names = list(kernels)
        for i, (kind, values) in enumerate(fr):
            for k in (names if i % 2 == 0 else names[::-1]):
                paths.cool()
                t0 = time.perf_counter()
                kernels[k](values, weights[k], prev[k], pose[k], *kept[k](reuse[k]), *paths.kernel_args)
                times[k][kind].append(time.perf_counter() - t0)
            largest = max(largest, float(np.abs(pose["baseline"] - pose["this tree"]).max()))
            for k in kernels:
                prev[k] = pose[k].copy()
    rev = subprocess.run(["git", "rev-parse", "--short", args.against], cwd=ROOT, capture_output=True,
                         text=True).stdout.strip()
    tree = hashlib.sha256((ROOT / SOURCE).read_bytes()).hexdigest()[:16]
    lines = [f"# python benchmarks/skin_kernel_ab.py {' '.join(sys.argv[1:] if argv is None else argv)}",
             f"# baseline {SOURCE} at {rev}; this tree's sha256 {tree}; {os.cpu_count()} CPUs; load average "
             + " / ".join(f"{x:.1f}" for x in os.getloadavg()),
             f"frame solve kernel, {args.config} (H = {paths.array.inverse.weights.hidden} per axis, output rank "
             f"{paths.array.inverse.rank}), interleaved; µs"]
    for kind in ("performance", "random"):
        lines.append(f"  {kind} ({len(times['baseline'][kind])} frames)      p1      p50      p99")
        pct = {k: np.percentile(np.array(times[k][kind]) * 1e6, [1, 50, 99]) for k in kernels}
        for k in kernels:
            lines.append(f"    {k:12s} {pct[k][0]:8.1f} {pct[k][1]:8.1f} {pct[k][2]:8.1f}")
        r = pct["this tree"] / pct["baseline"]
        lines.append(f"    ratio        {r[0]:8.2f} {r[1]:8.2f} {r[2]:8.2f}")
    lines.append(f"  largest pose difference, this tree vs baseline: {largest:.3g} (SI units)")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    if args.record:
        from models.atomic import write_bytes

        write_bytes(args.record, text.encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
