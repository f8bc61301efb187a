"""The architecture of the library, read from its source with ``ast``: imports flow one way
(``compress`` -> ``project`` -> ``basis``), no module imports another package's private
names, and the graph of imports between modules has no cycle, counting imports inside
functions too (a circle dodged by a lazy import is still a circle)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import basis

LIBRARY = Path(basis.__file__).parent.parent
PACKAGES = ("basis", "project", "compress")
#: Which packages each package may import from.
ALLOWED = {"basis": {"basis"}, "project": {"basis", "project"},
           "compress": {"basis", "project", "compress"}}


def modules(root: Path = LIBRARY) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the three packages."""
    out = {}
    for pkg in PACKAGES:
        for f in sorted((root / pkg).rglob("*.py")):
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = f
    return out


def imports(name: str, path: Path, known: set[str]) -> list[tuple[str, str | None]]:
    """(imported module, imported name or None) for every import statement of a module."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[:len(parts) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((sub, None) if sub in known else (base, a.name))
    return [(m, n) for m, n in out if m.split(".")[0] in PACKAGES]


def graph() -> dict[str, set[str]]:
    mods = modules()
    known = set(mods)
    g: dict[str, set[str]] = {}
    for name, path in mods.items():
        g[name] = set()
        for target, _ in imports(name, path, known):
            # importing a.b.c also runs a and a.b: the edge goes to the module named
            while target not in known and "." in target:
                target = target.rpartition(".")[0]
            if target in known and target != name:
                g[name].add(target)
    return g


def find_cycle(g: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for t in sorted(g.get(m, ())):
            if state.get(t) == 1:
                return path[path.index(t):] + [t]
            if t not in state and (c := visit(t)):
                return c
        state[m] = 2
        path.pop()
        return None

    for m in sorted(g):
        if m not in state and (c := visit(m)):
            return c
    return None


def _private(name: str) -> bool:
    """A leading underscore marks a private name; dunder names (``__version__``) are public."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def violations(name: str, path: Path) -> list[str]:
    """What module ``name`` imports against the rules of the module notes."""
    pkg = name.split(".")[0]
    out = []
    for target, imported in imports(name, path, set(modules())):
        other = target.split(".")[0]
        if other not in ALLOWED[pkg]:
            out.append(f"{name} imports {target}: {pkg} may not use {other}")
        elif other != pkg and any(_private(p) for p in target.split(".")):
            out.append(f"{name} imports the private module {target}")
        elif other != pkg and _private(imported or ""):
            out.append(f"{name} imports the private name {target}.{imported}")
    return out


@pytest.mark.parametrize("name", sorted(modules()))
def test_imports_flow_one_way_and_no_private_names_cross(name):
    assert violations(name, modules()[name]) == []


def test_no_import_cycle():
    assert find_cycle(graph()) is None, find_cycle(graph())


def test_the_checks_can_fail():
    # negative controls: a circle and a private import are found
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    fake = LIBRARY / "compress" / "cli" / "commands.py"
    found = imports("compress.cli.commands", fake, set(modules()))
    assert ("basis", "KINDS") in found  # absolute names are seen


def test_violations_are_found(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from basis.matrix import _lift\nimport compress\n"
                   "def f():\n    from project._paths import x\n")
    # the last import is inside its own package, where private names are its own business
    assert violations("project.bad", bad) == [
        "project.bad imports the private name basis.matrix._lift",
        "project.bad imports compress: project may not use compress",
    ]
