"""The architecture the layout promises (docs/architecture.md), checked on the source: the VO core
and the map never import the application; no import circle between the project's modules (also
through imports inside functions); no private name imported from another module; no test loads
a file from ``tools/``."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("slam", "vo", "mapping", "benchmarks")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def project_modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            found[module_name(path)] = path
    return found


def imports_of(path: Path, name: str, modules: dict) -> list[tuple[str, list[str]]]:
    """``(module imported, names taken from it)`` for every import of a project module in ``path``."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            names = [a.name for a in node.names]
            submodules = [f"{base}.{n}" for n in names if f"{base}.{n}" in modules]
            rest = [n for n in names if f"{base}.{n}" not in modules]
            if rest or node.module:         # (``from . import a, b`` imports the submodules only)
                out.append((base, rest))
            out += [(m, []) for m in submodules]
    return [(m, names) for m, names in out if m.split(".")[0] in PACKAGES and m in modules]


def graph() -> dict[str, set[str]]:
    modules = project_modules()
    return {name: {m for m, _ in imports_of(path, name, modules) if m != name} for name, path in modules.items()}


def test_vo_and_mapping_never_import_the_application():
    for name, deps in graph().items():
        if name.split(".")[0] in ("vo", "mapping"):
            assert not [d for d in deps if d.split(".")[0] in ("slam", "benchmarks")], name


def test_no_import_circle():
    edges = graph()
    def deps(name):
        return edges.get(name, set())

    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(deps(node)):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt):] + [nxt]
                raise AssertionError("import circle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node)


def test_no_private_name_imported_across_modules():
    modules = project_modules()
    offenders = []
    for name, path in modules.items():
        for module, names in imports_of(path, name, modules):
            offenders += [f"{name}: {module}.{n}" for n in names if n.startswith("_") and module != name]
    assert not offenders, offenders


def test_no_test_loads_tools():
    for path in (ROOT / "tests").glob("*.py"):
        if path.name == Path(__file__).name:
            continue
        text = path.read_text()
        for needle in ("spec_from_file_location", "sys.path.insert", "sys.path.append", '"tools"', "'tools'"):
            assert needle not in text, f"{path.name} loads a tool ({needle}): what a test needs lives in a package"
