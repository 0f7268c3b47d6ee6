"""Measure how readable the house is: the figures ``docs/architecture.md`` quotes, computed from the source.

Figures: annotations spelled ``Any`` (in the whole runtime and on the stream frame's path), the largest runtime
module, functions over 80 lines in ``runtime/`` and ``offline/fem/``, command-line modules and whether they follow
the one pattern (a module per command inside a pillar's ``cli`` package), and import cycles between the project's
modules (every import statement counts, those under ``if TYPE_CHECKING:`` aside).

    python -m tools.house_metrics                 # print the table
    python -m tools.house_metrics --write docs/house_metrics.md

The file it writes names the commit it measured; it is never edited by hand.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("likeness", "models", "drivers", "runtime", "sim_hardware", "offline", "studio")
#: Modules a stream frame passes from the socket to ``MotorBus.write`` (the path docs/architecture.md draws).
FRAME_PATH_PREFIXES = (
    "runtime/client_sockets.py", "runtime/server.py", "runtime/decoder.py", "runtime/messages.py",
    "runtime/wire_scan.py", "runtime/requests.py", "runtime/ipc.py", "runtime/loop_messages.py", "runtime/runner.py",
    "runtime/daemon.py", "runtime/core/", "runtime/solve.py", "runtime/skin.py", "runtime/safety.py",
    "runtime/shaper.py", "runtime/bus/", "drivers/base.py",
)
LONG_FUNCTION = 80


@dataclass(frozen=True)
class Figures:
    any_runtime: int
    any_frame_path: int
    largest_runtime: tuple[str, int]
    runtime_over_500: list[tuple[str, int]]
    long_functions: list[tuple[str, str, int]]
    cli_modules: list[str]
    cli_off_pattern: list[str]
    cycles: list[list[str]]
    contract_exceptions: int


def _sources(root: Path, package: str) -> Iterator[Path]:
    yield from sorted((root / package).rglob("*.py"))


def _module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_any(node: ast.expr | None) -> bool:
    """Whether an annotation mentions ``Any`` anywhere (``Any``, ``list[Any]``, ``dict[str, Any]``...)."""
    if node is None:
        return False
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        try:
            node = ast.parse(node.value, mode="eval").body
        except SyntaxError:
            return False
    return any((isinstance(n, ast.Name) and n.id == "Any") or (isinstance(n, ast.Attribute) and n.attr == "Any")
               for n in ast.walk(node))


def count_any(tree: ast.AST) -> int:
    """Parameters, returns and annotated attributes or variables whose annotation mentions ``Any``
    (``*args: Any`` and ``**kwargs: Any`` count too)."""
    n = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            args = node.args
            params = [*args.posonlyargs, *args.args, *args.kwonlyargs]
            params += [a for a in (args.vararg, args.kwarg) if a is not None]
            n += sum(_is_any(a.annotation) for a in params)
            n += _is_any(node.returns)
        elif isinstance(node, ast.AnnAssign):
            n += _is_any(node.annotation)
    return n


def long_functions(tree: ast.AST, rel: str) -> list[tuple[str, str, int]]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            length = (node.end_lineno or node.lineno) - node.lineno + 1
            if length > LONG_FUNCTION:
                out.append((rel, node.name, length))
    return out


def _type_checking_block(node: ast.stmt) -> bool:
    return isinstance(node, ast.If) and (
        (isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING")
        or (isinstance(node.test, ast.Attribute) and node.test.attr == "TYPE_CHECKING"))


def imports(tree: ast.Module, module: str, is_package: bool) -> set[str]:
    """Project modules ``module`` imports anywhere in its body (functions included, TYPE_CHECKING blocks not)."""
    found: set[str] = set()

    def visit(body: list[ast.stmt]) -> None:
        for stmt in body:
            if _type_checking_block(stmt):
                visit(stmt.orelse)  # type: ignore[attr-defined]
                continue
            for node in ast.walk(stmt):
                if isinstance(node, ast.Import):
                    found.update(alias.name for alias in node.names)
                elif isinstance(node, ast.ImportFrom):
                    base = node.module or ""
                    if node.level:
                        pkg = module.split(".") if is_package else module.split(".")[:-1]
                        pkg = pkg[: len(pkg) - (node.level - 1)]
                        base = ".".join([*pkg, base] if base else pkg)
                    found.add(base)
                    found.update(f"{base}.{alias.name}" for alias in node.names)

    visit(tree.body)
    return {m for m in found if m.split(".")[0] in PACKAGES}


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(10_000)

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return sorted(out)


def _cli_module(rel: str) -> bool:
    name = Path(rel).name
    return (name == "cli.py" or name.endswith("_cli.py") or "/cli/" in rel or "/commands/" in rel) and (
        not rel.startswith("tests/"))


def _follows_pattern(rel: str) -> bool:
    """A command module lives in a pillar's one ``cli`` package (``runtime/cli/NAME.py``...)."""
    parts = rel.split("/")
    return (len(parts) == 3 and parts[1] == "cli") or rel == "likeness/cli.py"


def _contract_exceptions(root: Path) -> int:
    """Imports the import contracts (``pyproject.toml``) let through as listed exceptions."""
    import tomllib

    doc = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))
    contracts = doc.get("tool", {}).get("importlinter", {}).get("contracts", [])
    return sum(len(c.get("ignore_imports", [])) for c in contracts)


def measure(root: Path = ROOT) -> Figures:
    """The figures of the source tree at ``root``."""
    any_runtime = any_path = 0
    sizes: list[tuple[str, int]] = []
    longs: list[tuple[str, str, int]] = []
    clis: list[str] = []
    graph: dict[str, set[str]] = {}
    for package in PACKAGES:
        for path in _sources(root, package):
            rel = path.relative_to(root).as_posix()
            text = path.read_text(encoding="utf-8")
            tree = ast.parse(text, filename=rel)
            module = _module_name(root, path)
            graph[module] = imports(tree, module, path.name == "__init__.py")
            if _cli_module(rel):
                clis.append(rel)
            if package == "runtime":
                n_any = count_any(tree)
                any_runtime += n_any
                sizes.append((rel, len(text.splitlines())))
            if rel.startswith(FRAME_PATH_PREFIXES):
                any_path += count_any(tree)
            if package == "runtime" or rel.startswith("offline/fem/"):
                longs += long_functions(tree, rel)
    known = set(graph)
    resolved = {m: {t if t in known else t.rsplit(".", 1)[0] for t in targets} & known - {m}
                for m, targets in graph.items()}
    # ``import a.b.c`` also runs a/__init__ and a/b/__init__, but a package's own __init__ is not a cycle partner
    # through that alone: only the modules named count.
    sizes.sort(key=lambda x: -x[1])
    return Figures(
        any_runtime=any_runtime,
        any_frame_path=any_path,
        largest_runtime=sizes[0],
        runtime_over_500=[s for s in sizes if s[1] > 500],
        long_functions=sorted(longs, key=lambda x: -x[2]),
        cli_modules=sorted(clis),
        cli_off_pattern=sorted(c for c in clis if not _follows_pattern(c)),
        cycles=import_cycles(resolved),
        contract_exceptions=_contract_exceptions(root),
    )


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def render(f: Figures, target: str = "docs/house_metrics.md") -> str:
    lines = [
        "# House figures",
        "",
        f"Written by `python -m tools.house_metrics --write {target}` at commit {_commit()}; not edited "
        "by hand.",
        "",
        "| figure | value |",
        "|---|---|",
        f"| annotations spelled `Any` in `runtime/` | {f.any_runtime} |",
        f"| annotations spelled `Any` on the stream frame's path | {f.any_frame_path} |",
        f"| largest runtime module | `{f.largest_runtime[0]}`, {f.largest_runtime[1]} lines |",
        f"| runtime modules over 500 lines | {len(f.runtime_over_500)} |",
        f"| functions over {LONG_FUNCTION} lines in `runtime/` and `offline/fem/` | {len(f.long_functions)} |",
        f"| command-line modules | {len(f.cli_modules)} |",
        f"| command-line modules outside the one pattern (`PILLAR/cli/COMMAND.py`) | {len(f.cli_off_pattern)} |",
        f"| import cycles between modules (TYPE_CHECKING imports aside) | {len(f.cycles)} |",
        f"| import-contract exceptions (`ignore_imports`) | {f.contract_exceptions} |",
        "",
    ]
    if f.runtime_over_500:
        lines += ["Runtime modules over 500 lines: " + ", ".join(f"`{p}` ({n})" for p, n in f.runtime_over_500), ""]
    if f.long_functions:
        lines += ["Functions over 80 lines: " + ", ".join(f"`{p}:{name}` ({n})" for p, name, n in f.long_functions),
                  ""]
    if f.cli_off_pattern:
        lines += ["Command-line modules outside the pattern: " + ", ".join(f"`{p}`" for p in f.cli_off_pattern), ""]
    if f.cycles:
        lines += ["Import cycles:", ""] + [f"- {' ↔ '.join(c)}" for c in f.cycles] + [""]
    return "\n".join(lines)


def measure_commit(commit: str) -> Figures:
    """The figures of ``commit`` (its tree exported into a temporary folder)."""
    import tarfile
    import tempfile

    with tempfile.TemporaryDirectory(prefix="house-") as tmp:
        archive = subprocess.run(["git", "archive", "--format=tar", commit], cwd=ROOT, capture_output=True,
                                 check=True).stdout
        import io

        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(tmp, filter="data")
        return measure(Path(tmp))


BEGIN, END = "<!-- house-figures: begin -->", "<!-- house-figures: end -->"


def comparison(before: Figures, now: Figures, commit: str) -> str:
    """The before/now table ``docs/architecture.md`` carries between its house-figures markers."""
    rows = [
        ("annotations mentioning `Any` on the stream frame's path", before.any_frame_path, now.any_frame_path),
        ("annotations mentioning `Any` in `runtime/`", before.any_runtime, now.any_runtime),
        ("largest runtime module", f"`{before.largest_runtime[0]}`, {before.largest_runtime[1]} lines",
         f"`{now.largest_runtime[0]}`, {now.largest_runtime[1]} lines"),
        ("runtime modules over 500 lines", len(before.runtime_over_500), len(now.runtime_over_500)),
        (f"functions over {LONG_FUNCTION} lines in `runtime/` and `offline/fem/`", len(before.long_functions),
         len(now.long_functions)),
        ("command-line modules outside the one pattern", f"{len(before.cli_off_pattern)} of {len(before.cli_modules)}",
         f"{len(now.cli_off_pattern)} of {len(now.cli_modules)}"),
        ("import cycles between modules", len(before.cycles), len(now.cycles)),
        ("import-contract exceptions (`ignore_imports`)", before.contract_exceptions, now.contract_exceptions),
    ]
    lines = [BEGIN, f"Written by `python -m tools.house_metrics --before {commit} --architecture "
             "docs/architecture.md` at commit " + _commit() + "; not edited by hand.", "",
             f"| figure | before (`{commit}`) | now |", "|---|---|---|"]
    lines += [f"| {name} | {b} | {n} |" for name, b, n in rows]
    return "\n".join([*lines, END])


def write_comparison(path: Path, before_commit: str) -> None:
    """Replace the block between the house-figures markers of ``path`` with the before/now table."""
    from models.atomic import write_text

    text = path.read_text(encoding="utf-8")
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{path}: no {BEGIN} ... {END} block to fill")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    write_text(path, head + comparison(measure_commit(before_commit), measure(), before_commit) + tail)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", type=Path, default=None, help="write the table to this markdown file")
    parser.add_argument("--before", default=None, help="a commit to compare with (needs --architecture)")
    parser.add_argument("--architecture", type=Path, default=None,
                        help="fill this file's house-figures block with the before/now table")
    args = parser.parse_args(argv)
    if args.architecture is not None:
        if args.before is None:
            parser.error("--architecture needs --before COMMIT")
        write_comparison(args.architecture, args.before)
        print(f"wrote the house figures into {args.architecture}")
    if args.write is None:
        if args.architecture is None:
            print(render(measure()))
        return 0
    text = render(measure(), args.write.as_posix())
    from models.atomic import write_text

    write_text(args.write, text)
    print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
