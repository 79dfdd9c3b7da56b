"""The package's shape: imports go down the data flow only, SUMO has one boundary."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "macromicro_sumo"

# Lower rank = further down the data flow; a module may import only from lower ranks or
# from its own folder (whose modules must not form a cycle either).
RANK = {
    "errors": 0,
    "files": 1,
    "progress": 1,
    "checkpoints": 2,
    "scenario": 3,
    "manifest": 4,
    "sumo": 4,
    "road": 5,
    "data": 6,
    "truth": 7,
    "fielddata": 6,  # reads files into the ground truth's frames: truth/ may build on it
    "generator": 8,
    "env": 9,
    "policy": 10,
    "evaluation": 11,
    "deploy": 12,
    "report": 13,
    "pipeline": 14,
    "batch": 15,
    "cli": 16,
}


@functools.cache  # parsed once for the module's tests (they only read the trees)
def _modules() -> dict[str, ast.Module]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE).with_suffix("")
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        out[name] = ast.parse(path.read_text())
    return out


def _imports(tree: ast.AST) -> list[tuple[str, int]]:
    """(imported module, line) for every ``macromicro_sumo`` import anywhere in ``tree``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("macromicro_sumo"):
            base = node.module.removeprefix("macromicro_sumo").lstrip(".")
            for alias in node.names:
                found.append((f"{base}.{alias.name}".strip("."), node.lineno))
        elif isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names if "macromicro_sumo" in a.name]
    return found


def _owner(name: str, modules: dict[str, ast.Module]) -> str:
    """The module an imported dotted name lives in (``data.macro.psi`` -> ``data.macro``)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name


def test_imports_go_down_the_data_flow_only():
    modules = _modules()
    wrong = []
    for name, tree in modules.items():
        for imported, line in _imports(tree):
            target = _owner(imported, modules)
            here, there = name.split(".")[0], target.split(".")[0]
            if here != there and RANK[there] >= RANK[here]:
                wrong.append(f"{name}:{line} imports {target} (up the flow)")
    assert not wrong, "\n".join(wrong)


def test_no_import_cycles_and_no_imports_inside_functions():
    modules = _modules()
    graph = {name: set() for name in modules}
    inside = []
    for name, tree in modules.items():
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                inside += [f"{name}:{line}" for _, line in _imports(node)]
        for node in tree.body:
            if id(node) in top:
                for imported, _ in _imports(node):
                    target = _owner(imported, modules)
                    if target and target != name and target in modules:
                        graph[name].add(target)
    assert not inside, "imports inside functions: " + ", ".join(inside)
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in graph[node]:
            if nxt in name_of_package(node):
                continue
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*path, node, nxt]))
            if nxt not in state:
                visit(nxt, [*path, node])
        state[node] = 2

    def name_of_package(node: str) -> set[str]:
        # ``pkg/__init__`` is imported implicitly by its own modules: not a cycle.
        return {node.rpartition(".")[0]} if "." in node else set()

    for name in modules:
        if name not in state:
            visit(name, [])


def test_only_the_sumo_boundary_imports_libsumo_or_traci():
    importers = set()
    for name, tree in _modules().items():
        for node in ast.walk(tree):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            if any(n.split(".")[0] in ("libsumo", "traci") for n in names):
                importers.add(name)
    assert importers == {"sumo.simulation"}


def test_no_module_imports_another_modules_private_names():
    private = []
    for name, tree in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(
                "macromicro_sumo"
            ):
                private += [f"{name}: {a.name}" for a in node.names if a.name.startswith("_")]
    assert not private, "private names imported across modules: " + ", ".join(private)


def test_no_module_needs_more_than_500_lines():
    long = {
        str(p.relative_to(PACKAGE)): n
        for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > 500
    }
    assert not long, f"split these by concept: {long}"
