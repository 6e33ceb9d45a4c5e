"""The package's architecture, checked from its source with ``ast``: no import cycles (imports
inside functions included), core/ independent of the layers above it, and a small top level."""
import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "mi_grg"
ROOTS = {PKG: ("mi_grg",), REPO / "plugins": ("mi_grg", "plugins")}   # as pyproject installs


def _modules() -> dict:
    """module name -> (path, is_package) for every .py file of mi_grg and its plugins."""
    out = {}
    for root, prefix in ROOTS.items():
        for p in sorted(root.rglob("*.py")):
            parts = prefix + p.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = (p, p.name == "__init__.py")
    return out


def _resolve(name: str, known: dict) -> str | None:
    """The longest known module that ``name`` (a module or a name inside one) refers to."""
    while name:
        if name in known:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph(lazy: bool = True) -> dict:
    """module -> {mi_grg modules it imports anywhere in its source}. ``from X import y`` counts
    as importing X and, when y is a module, X.y; relative imports are resolved. With
    ``lazy``, the lazy public names of ``mi_grg.__init__`` (the strings in ``_LAZY``, imported
    on first attribute access) count as imports of the package too."""
    known = _modules()
    graph = {}
    for mod, (path, is_pkg) in known.items():
        deps = set()
        package = mod if is_pkg else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")
                    anchor = anchor[:len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                targets = [f"{base}.{a.name}" for a in node.names] + [base]
            elif (lazy and isinstance(node, ast.Assign) and mod == "mi_grg"
                  and any(isinstance(t, ast.Name) and t.id == "_LAZY" for t in node.targets)):
                targets = [v.value for v in node.value.values]
            for t in targets:
                if t == "mi_grg" or t.startswith("mi_grg."):
                    r = _resolve(t, known)
                    if r and r != mod:
                        deps.add(r)
        graph[mod] = deps
    return graph


def find_cycle(graph: dict) -> list | None:
    """One cycle as [a, b, ..., a], or None (iterative depth-first search)."""
    state = {}
    for start in graph:
        if state.get(start):
            continue
        stack = [(start, iter(sorted(graph[start])))]
        path = [start]
        state[start] = 1
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                state[node] = 2
                stack.pop()
                path.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            elif not state.get(nxt) and nxt in graph:
                state[nxt] = 1
                stack.append((nxt, iter(sorted(graph[nxt]))))
                path.append(nxt)
    return None


def test_no_import_cycles():
    graph = import_graph()
    # the walker sees every kind of import (else an empty graph would pass)
    assert "mi_grg.core.geometry" in graph["mi_grg.core.projector"]        # module level
    assert "mi_grg.lab.report" in graph["mi_grg.cli"]                      # in a function
    assert "mi_grg.lab.runner" in graph["mi_grg"]                          # _LAZY
    # _LAZY's names are imported when first used, after `import mi_grg` has finished, so they
    # close no cycle; the package's eager imports (variant, core.geometry) do count
    eager = import_graph(lazy=False)
    assert "mi_grg.core.geometry" in eager["mi_grg"]
    cycle = find_cycle(eager)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) in (
        ["a", "b", "c", "a"], ["b", "c", "a", "b"], ["c", "a", "b", "c"])
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set(), "d": {"a", "c"}}) is None


def test_layers():
    graph = import_graph()
    above = ("training", "lab", "classical", "evaluation")
    for mod, deps in graph.items():
        if mod.startswith("mi_grg.core"):
            bad = sorted(d for d in deps if d.split(".")[1:2] and d.split(".")[1] in above)
            assert not bad, f"{mod} (core) imports {bad}"
    # only the command line (and the package's lazy public name) reads the report
    users = sorted(m for m, deps in graph.items() if "mi_grg.lab.report" in deps)
    assert users == ["mi_grg", "mi_grg.cli"], users


def test_top_level_is_small():
    top = sorted(p.name for p in PKG.glob("*.py"))
    subpackages = sorted(p.name for p in PKG.iterdir() if (p / "__init__.py").is_file())
    assert {"core", "training", "lab"} <= set(subpackages)
    assert len(top) <= 6, top


def test_scripts_import_what_exists():
    """bench/, scripts/, docs/, experiments/ and experiments/studies/ scripts run outside the
    test suite; a module that moved must not leave them importing a name that is gone."""
    import importlib
    missing = []
    for folder in ("bench", "scripts", "docs", "experiments", "experiments/studies"):
        for path in sorted((REPO / folder).glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mi_grg"):
                    names = [f"{node.module}.{a.name}" for a in node.names]
                elif isinstance(node, ast.Import):
                    names = [a.name for a in node.names if a.name.startswith("mi_grg")]
                else:
                    continue
                for name in names:
                    module, _, attr = name.rpartition(".")
                    try:
                        importlib.import_module(name)
                        continue
                    except ImportError:
                        pass
                    try:
                        found = hasattr(importlib.import_module(module), attr)
                    except ImportError:
                        found = False
                    if not found:
                        missing.append(f"{path.relative_to(REPO)}: {name}")
    assert not missing, missing
