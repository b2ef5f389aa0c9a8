"""The import graph runs one way: each stage imports only the stages below it, and nothing
imports the command line. Reads the sources (every import, including those inside functions)
rather than importing them, so a lazy import cannot hide an arrow that runs back up."""
import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "fmubuilder"

# Lowest first. A module may import modules of a lower rank and of its own unit; one unit is a
# top-level module or sub-package of fmubuilder. See docs/ARCHITECTURE.md.
RANKS = {
    "errors": 0, "_lazy": 0, "progress": 0,
    "files": 1, "build": 1, "score": 1,
    "fmi": 2,
    "simulation": 3,
    "data": 4, "inspect_fmu": 4,
    "neural": 5, "diagnose": 5,
    "export": 6, "synth": 6,
    "hybridize": 7, "examples_zoo": 7,
    "demo": 8, "batch": 8,
    "cli": 9, "__main__": 9,
}


def _unit(module: str) -> str:
    """'fmubuilder.neural.train' -> 'neural'; 'fmubuilder' -> ''."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: pathlib.Path) -> set[str]:
    """The fmubuilder modules that `path` imports, resolved to absolute names."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("fmubuilder"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("fmubuilder"):
                found.add(target)
                # `from . import x` may name a submodule: count it as one.
                found.update(f"{target}.{a.name}" for a in node.names if _is_module(f"{target}.{a.name}"))
    return found


def _is_module(name: str) -> bool:
    path = PACKAGE.parent.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _graph() -> dict[str, set[str]]:
    return {_module_name(path): _imports(path) for path in sorted(PACKAGE.rglob("*.py"))}


def test_every_unit_has_a_rank():
    units = {_unit(module) for module in _graph()} - {""}
    assert units <= RANKS.keys(), f"give these a rank in RANKS: {sorted(units - RANKS.keys())}"


def test_imports_run_one_way():
    upward = []
    for module, imported in _graph().items():
        source = _unit(module)
        for target in imported:
            dest = _unit(target)
            if source and dest and dest != source and RANKS.get(dest, 99) >= RANKS.get(source, 99):
                upward.append(f"{module} -> {target}")
    assert not upward, "imports that run sideways or back up:\n" + "\n".join(sorted(upward))


def test_no_import_cycles():
    graph = _graph()
    known = set(graph)

    def resolve(name: str) -> str | None:
        # `from .x import y` names a module or a name in one; keep the longest known prefix.
        while name and name not in known:
            name = name.rpartition(".")[0]
        return name or None

    edges = {m: {t for t in map(resolve, targets) if t and t != m and not m.startswith(t + ".")}
             for m, targets in graph.items()}
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(node: str):
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                cycle = path[path.index(nxt):] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        path.pop()
        state[node] = 2

    for module in sorted(edges):
        if module not in state:
            visit(module)
