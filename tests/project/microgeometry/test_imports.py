"""The imports inside project.microgeometry: a graph without cycles, built at module level.

Every ``import`` statement of every module of the subpackage is read with ``ast`` (those inside
functions included) and its target resolved to a sibling module; the graph of these
imports must have no cycle (a circle would force imports inside functions to dodge it), and
no sibling is imported inside a function. The private names of the subpackage stay inside it:
no module of the library outside it imports them. The public names of ``trace.py`` stay
importable where they always were.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

import project
import project.microgeometry

PACKAGE = "project.microgeometry"
ROOT = Path(project.microgeometry.__file__).parent
LIBRARY = Path(project.__file__).parent.parent  # holds basis/, project/, compress/


def _targets(node: ast.AST, siblings: set[str]) -> list[str]:
    """The sibling modules (or ``__init__``) an import statement inside the package reaches."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom):
        if node.level:  # relative: resolve against the package
            base = PACKAGE.split(".")
            if node.level > 1:
                base = base[:len(base) - node.level + 1]
            full = ".".join(base + ([node.module] if node.module else []))
        else:
            full = node.module or ""
        # ``from package import name``: name may itself be a module
        names = [full] + [f"{full}.{a.name}" for a in node.names]
    else:
        return []
    out = []
    for name in names:
        if name == PACKAGE:
            out.append("__init__")
        elif name.startswith(PACKAGE + "."):
            first = name[len(PACKAGE) + 1:].split(".")[0]
            if first in siblings:
                out.append(first)
    # ``from .bvh import X`` gives "bvh" (and "__init__" only for ``from . import X`` of a
    # non-module name): drop the package itself when a module was named
    if len(out) > 1 and "__init__" in out:
        out.remove("__init__")
    return sorted(set(out))


def import_graph(sources: dict[str, str]) -> dict[str, dict[str, bool]]:
    """{module: {imported sibling: at module level?}} for module name -> source text."""
    siblings = set(sources)
    graph: dict[str, dict[str, bool]] = {}
    for module, text in sources.items():
        tree = ast.parse(text)
        top = {id(n) for n in tree.body}
        edges: dict[str, bool] = {}
        for node in ast.walk(tree):
            for target in _targets(node, siblings):
                if target != module:
                    edges[target] = edges.get(target, False) or id(node) in top
        graph[module] = edges
    return graph


def find_cycle(graph: dict[str, dict[str, bool]]) -> list[str] | None:
    """One cycle of the graph as a list of modules (first repeated last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph.get(m, {})):
            if state.get(n) == 1:
                return path[path.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        path.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def _sources() -> dict[str, str]:
    return {p.stem: p.read_text() for p in sorted(ROOT.glob("*.py"))}


def test_checker_finds_circles():
    # negative controls: a circle closed by an import inside a function, the package's own
    # __init__ imported back, and a clean chain
    circle = {"a": "from .b import f\n",
              "b": "def g():\n    from project.microgeometry.a import h\n"}
    assert import_graph(circle) == {"a": {"b": True}, "b": {"a": False}}
    assert find_cycle(import_graph(circle)) in (["a", "b", "a"], ["b", "a", "b"])
    back = {"__init__": "from .a import f\n", "a": "from . import Scene\n"}
    assert find_cycle(import_graph(back)) == ["__init__", "a", "__init__"]
    chain = {"a": "import numpy\nfrom ..io import x\n", "b": "from . import a\n",
             "c": "from .b import y\nfrom .a import z\n"}
    assert import_graph(chain) == {"a": {}, "b": {"a": True}, "c": {"a": True, "b": True}}
    assert find_cycle(import_graph(chain)) is None


def test_microgeometry_imports_have_no_cycle():
    graph = import_graph(_sources())
    assert {"bvh", "trace", "scene", "wavefront"} <= set(graph)
    cycle = find_cycle(graph)
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}"
    # the layering the shared kernels give: _paths at the bottom of the tracers
    assert set(graph["_paths"]) <= {"materials"}
    assert "_paths" in graph["bvh"] and "trace" not in graph["bvh"]


def test_siblings_are_imported_at_module_level():
    # an import of a sibling inside a function is only ever needed to dodge a circle
    late = {m: sorted(t for t, top in edges.items() if not top)
            for m, edges in import_graph(_sources()).items()}
    assert not {m: t for m, t in late.items() if t}


def test_private_names_stay_inside_the_subpackage():
    # library modules outside project.microgeometry import only its public names
    paths = [p for top in ("basis", "project", "compress") for p in (LIBRARY / top).rglob("*.py")
             if ROOT not in p.parents]
    assert len(paths) > 20
    bad = []
    for path in sorted(paths):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                private = [a.name for a in node.names
                           if a.name.startswith(PACKAGE + ".") and "._" in a.name]
            elif isinstance(node, ast.ImportFrom):
                module = node.module or ""
                inside = module.startswith(PACKAGE) or (
                    node.level == 1 and module.startswith("microgeometry"))
                private = [a.name for a in node.names if a.name.startswith("_")] + (
                    [module] if "._" in module else [])
                private = private if inside else []
            else:
                continue
            if private:
                bad.append(f"{path.relative_to(LIBRARY)}: {private}")
    assert not bad


def test_public_names_of_trace_stay_importable():
    from project.microgeometry import trace as public_trace
    from project.microgeometry.trace import (
        MAX_BOUNCES,
        MAX_STEPS,
        ROULETTE,
        Paths,
        incident_directions,
        trace,
    )

    # Paths._fields: the documented namedtuple API, public despite the underscore
    assert trace is public_trace and Paths._fields[0] == "directions"
    assert (MAX_BOUNCES, MAX_STEPS, ROULETTE) == (10_000, 1_000_000, 0.05)
    assert incident_directions(3, np.uint64(1), 0, True).shape == (3, 3)
