"""Readability targets of mi_grg (issue "a codebase a newcomer can read in an afternoon").

    .venv/bin/python scripts/readability_check.py        # each target: count, PASS / FAIL
    .venv/bin/python scripts/readability_check.py -v     # also every history line
    .venv/bin/python scripts/readability_check.py --root DIR   # another checkout

Exits 1 when a target fails.

Targets: README.md <= 150 lines; no module in mi_grg/ or plugins/ over 600 lines; no
function in mi_grg/ (plugins/ included, installed as mi_grg.plugins) over 80 lines;
exactly one function in mi_grg/ calls ``projection_loss`` (the training step is written
once: mi_grg.training.step); no import cycle between mi_grg's modules (every import,
function-local ones included); at most 5 comment / docstring lines that carry history
(a commit hash, a date, an issue or session number, a measured dB / ms / s figure): such
figures belong in docs/benchmarks.md, the comment keeps the reason.
"""
from __future__ import annotations

import ast
import io
import re
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"mi_grg": ROOT / "mi_grg", "mi_grg.plugins": ROOT / "plugins"}

MAX_README_LINES = 150
MAX_FUNCTION_LINES = 80
MAX_HISTORY_LINES = 5
MAX_MODULE_LINES = 600
# the one function that composes the training loss (every iteration calls it)
LOSS_FUNCTION = "projection_loss"

# a word of 7-40 hex digits with at least one digit and one letter (a commit hash), a date,
# an issue / session number, or a measured figure in dB, ms or s
_HISTORY = re.compile(
    r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"
    r"|\b20\d\d-\d\d(-\d\d)?\b"
    r"|\b(issue|session)s? #?\d+"
    r"|[+-]?\d+(\.\d+)? ?(dB|ms|s)\b(?!\^)",
    re.IGNORECASE)


def modules(packages=None) -> dict:
    """{dotted module name: path} of every module of ``packages`` ({package name: folder};
    default: mi_grg with its plugins)."""
    out = {}
    for pkg, base in (packages or PACKAGES).items():
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join([pkg, *parts])] = path
    return out


def long_functions(limit: int = MAX_FUNCTION_LINES, packages=None) -> list:
    """[(path, line, qualified name, length)] of functions longer than ``limit`` lines
    (length = end_lineno - lineno + 1, decorators and docstring included)."""
    found = []
    for path in modules(packages).values():
        tree = ast.parse(path.read_text(), str(path))
        stack = [(tree, "")]
        while stack:
            node, prefix = stack.pop()
            for child in ast.iter_child_nodes(node):
                name = prefix
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}"
                    if not isinstance(child, ast.ClassDef):
                        length = child.end_lineno - child.lineno + 1
                        if length > limit:
                            found.append((path, child.lineno, name, length))
                    name += "."
                stack.append((child, name))
    return sorted(found, key=lambda f: (str(f[0]), f[1]))


def long_modules(limit: int = MAX_MODULE_LINES, packages=None) -> list:
    """[(path, lines)] of modules longer than ``limit`` lines."""
    found = []
    for path in modules(packages).values():
        n = len(path.read_text().splitlines())
        if n > limit:
            found.append((path, n))
    return found


def callers(callee: str = LOSS_FUNCTION, packages=None) -> list:
    """[(path, qualified name)] of the functions whose own body (nested functions apart)
    calls ``callee`` by name or as an attribute (``losses.projection_loss(...)``)."""
    found = []
    for path in modules(packages).values():
        tree = ast.parse(path.read_text(), str(path))
        stack = [(tree, "", None)]
        while stack:
            node, prefix, owner = stack.pop()
            for child in ast.iter_child_nodes(node):
                name, own = prefix, owner
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}."
                    own = None if isinstance(child, ast.ClassDef) else name[:-1]
                elif isinstance(child, ast.Call) and own is not None:
                    f = child.func
                    called = f.id if isinstance(f, ast.Name) else getattr(f, "attr", None)
                    if called == callee and (path, own) not in found:
                        found.append((path, own))
                stack.append((child, name, own))
    return sorted(found, key=lambda f: (str(f[0]), f[1]))


def _imported(name: str, node, known: dict) -> set:
    """Modules of ``known`` that an import node of module ``name`` refers to."""
    is_pkg = known[name].name == "__init__.py"
    if isinstance(node, ast.Import):
        targets = [a.name for a in node.names]
    else:
        base = node.module or ""
        if node.level:
            parts = name.split(".")[:len(name.split(".")) - node.level + (1 if is_pkg else 0)]
            base = ".".join(parts + ([base] if base else []))
        targets = [f"{base}.{a.name}" for a in node.names] + [base]
    out = set()
    for t in targets:
        while t and t not in known:          # a name inside a module: the module
            t = t.rpartition(".")[0]
        if t and t != name:
            out.add(t)
    return out


def import_graph(packages=None) -> dict:
    """{module: set of package modules it imports}, every import statement included
    (function-local ones too)."""
    known = modules(packages)
    graph = {}
    for name, path in known.items():
        tree = ast.parse(path.read_text(), str(path))
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                deps |= _imported(name, node, known)
        graph[name] = deps
    return graph


def import_cycles(packages=None) -> list:
    """Strongly connected components of more than one module of the package-level import
    graph (Tarjan): each a sorted list of module names."""
    graph = import_graph(packages)
    index, low, on, stack, sccs = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                sccs.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in graph:
        if v not in index:
            visit(v)
    return sccs


def history_lines(packages=None) -> list:
    """[(path, line, text)] of comment and docstring lines that carry history: the
    comment's text of a code line, every line of a docstring."""
    found = []
    for path in modules(packages).values():
        src = path.read_text()
        lines = src.splitlines()
        texts = {}
        for tok in tokenize.generate_tokens(io.StringIO(src).readline):
            if tok.type == tokenize.COMMENT:
                texts[tok.start[0]] = tok.string
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                body = node.body
                if body and isinstance(body[0], ast.Expr) \
                        and isinstance(body[0].value, ast.Constant) \
                        and isinstance(body[0].value.value, str):
                    for ln in range(body[0].lineno, body[0].end_lineno + 1):
                        texts[ln] = lines[ln - 1]
        for ln in sorted(texts):
            if _HISTORY.search(texts[ln]):
                found.append((path, ln, lines[ln - 1].strip()))
    return found


def main() -> int:
    root = Path(sys.argv[sys.argv.index("--root") + 1]) if "--root" in sys.argv else ROOT
    packages = {"mi_grg": root / "mi_grg", "mi_grg.plugins": root / "plugins"}
    readme = len((root / "README.md").read_text().splitlines())
    longf = long_functions(packages=packages)
    longm = long_modules(packages=packages)
    loss = callers(packages=packages)
    cycles = import_cycles(packages)
    hist = history_lines(packages)
    rows = [("README.md lines", readme, MAX_README_LINES),
            (f"modules over {MAX_MODULE_LINES} lines", len(longm), 0),
            (f"functions over {MAX_FUNCTION_LINES} lines", len(longf), 0),
            ("package import cycles", len(cycles), 0),
            ("comment / docstring lines carrying history", len(hist), MAX_HISTORY_LINES)]
    verbose = "-v" in sys.argv[1:]
    for p, n in longm:
        print(f"  long module: {p.relative_to(root)} ({n} lines)")
    for p, name in loss:
        print(f"  calls {LOSS_FUNCTION}: {p.relative_to(root)}:{name}")
    for f in longf:
        print(f"  long: {f[0].relative_to(root)}:{f[1]} {f[2]} ({f[3]} lines)")
    for c in cycles:
        print("  cycle: " + " <-> ".join(c))
    for p, ln, text in hist if verbose else hist[:0]:
        print(f"  history: {p.relative_to(root)}:{ln}: {text}")
    ok = True
    for label, count, limit in rows:
        passed = count <= limit
        ok &= passed
        print(f"{label:45s} {count:6d}  (target <= {limit})  {'PASS' if passed else 'FAIL'}")
    passed = len(loss) == 1
    ok &= passed
    print(f"{'functions calling ' + LOSS_FUNCTION:45s} {len(loss):6d}  (target == 1)  "
          f"{'PASS' if passed else 'FAIL'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
