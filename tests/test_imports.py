"""No import cycles between the modules of artnvg_core and of the node pack, lazy imports included, and
no import from a lower floor of the house to a higher one (:data:`FLOORS`).

Every module's source is parsed (nothing is imported): each ``import`` and ``from ... import``
statement, at the top or inside a function, is an arrow to the module it names; ``from P import
name`` points at ``P.name`` when that is a module of the package, else at ``P``. A cycle of arrows
is a circle that only import order or a lazy import keeps from failing (docs/design.md, "Layout").
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("artnvg_core", "nodes")
# The floors of the house (docs/design.md, "Layout"), ground first: a module imports only from its own floor
# or below. A room is a top-level module or package of artnvg_core (its modules with it), or the node pack.
FLOORS = (
    ("artnvg_core", "artnvg_core.scene", "artnvg_core.fileio", "artnvg_core.images", "artnvg_core.statedict",
     "artnvg_core.progress", "artnvg_core.devices", "artnvg_core.tensor_tree", "artnvg_core.tensor_files",
     "artnvg_core.background", "artnvg_core.triton_runtime", "artnvg_core.style_image",
     "artnvg_core.json_objects", "artnvg_core.counted", "artnvg_core.notes"),  # the data and the plumbing
    ("artnvg_core.cameras", "artnvg_core.cluster", "artnvg_core.losses", "artnvg_core.preview"),
    ("artnvg_core.formats", "artnvg_core.activated", "artnvg_core.raster", "artnvg_core.grouping",
     "artnvg_core.balanced_kmeans", "artnvg_core.key_views"),
    ("artnvg_core.orbit", "artnvg_core.selection", "artnvg_core.blend", "artnvg_core.diffusion"),
    ("artnvg_core.finetune", "artnvg_core.presets"),  # the two stages' settings and the finetune
    ("artnvg_core.metrics", "artnvg_core.stylize"),  # the measures and the whole job
    ("artnvg_core.cli", "nodes"),  # the two faces: the command line and ComfyUI's nodes
    ("artnvg_core.__main__",),
)


def module_names(root: Path = ROOT, packages=PACKAGES) -> dict[str, Path]:
    """Dotted module name -> source file, for every .py file of ``packages`` (``pkg/__init__.py`` is ``pkg``)."""
    names = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


def imported_modules(name: str, path: Path, known: set[str]) -> set[str]:
    """The modules of ``known`` that ``name`` (source ``path``) imports anywhere in its body."""
    is_package = path.name == "__init__.py"
    targets = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")[: len(name.split(".")) - node.level + (1 if is_package else 0)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            candidates = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else source
                          for alias in node.names]
        else:
            continue
        for candidate in candidates:
            while candidate and candidate not in known:  # `import a.b.c` of a name inside a module
                candidate = candidate.rpartition(".")[0]
            if candidate and candidate != name:
                targets.add(candidate)
    return targets


def import_graph(root: Path = ROOT, packages=PACKAGES) -> dict[str, set[str]]:
    names = module_names(root, packages)
    return {name: imported_modules(name, path, set(names)) for name, path in names.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_no_module_imports_itself_back():
    graph = import_graph()
    assert len(graph) > 80 and "artnvg_core.raster" in graph["artnvg_core.orbit"]  # the parse sees the package
    circles = cycles(graph)
    assert not circles, "import cycles:\n" + "\n".join(
        " <-> ".join(circle) + ": " + "; ".join(f"{a} -> {b}" for a in circle for b in sorted(graph[a]) if b in circle)
        for circle in circles)


def test_lazy_relative_and_submodule_imports_are_arrows(tmp_path):
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("def f():\n    from .sub import b  # lazy, a submodule\n")
    (package / "sub" / "__init__.py").write_text("from .b import g\n")
    (package / "sub" / "b.py").write_text("import pkg.c\n")
    (package / "c.py").write_text("from pkg import a\n")
    graph = import_graph(tmp_path, ("pkg",))
    assert graph == {"pkg": set(), "pkg.a": {"pkg.sub.b"}, "pkg.sub": {"pkg.sub.b"}, "pkg.sub.b": {"pkg.c"},
                     "pkg.c": {"pkg.a"}}
    assert cycles(graph) == [["pkg.a", "pkg.c", "pkg.sub.b"]]
    (package / "c.py").write_text("from pkg.sub import g\n")  # a name of a package: the package
    assert cycles(import_graph(tmp_path, ("pkg",))) == [["pkg.c", "pkg.sub", "pkg.sub.b"]]


def room_of(module: str) -> str:
    """The room of ``module``: ``nodes`` for the node pack, else its top-level module or package."""
    return "nodes" if module.split(".")[0] == "nodes" else ".".join(module.split(".")[:2])


def arrows_up(graph: dict[str, set[str]], floors=FLOORS) -> list[str]:
    """``A -> B`` for each import of ``graph`` from a room on a lower floor to one on a higher floor, and
    ``A: no floor`` for a module whose room :data:`FLOORS` does not name."""
    floor = {room: level for level, rooms in enumerate(floors) for room in rooms}
    found = [f"{a}: no floor (add its room to FLOORS)" for a in sorted(graph) if room_of(a) not in floor]
    found += [f"{a} -> {b}" for a in sorted(graph) for b in sorted(graph[a])
              if room_of(a) in floor and room_of(b) in floor and floor[room_of(b)] > floor[room_of(a)]]
    return found


def test_no_module_imports_from_a_higher_floor():
    graph = import_graph()
    assert "artnvg_core.raster.step_renderer" in graph["artnvg_core.finetune.loop"]  # the parse sees the arrows
    assert not arrows_up(graph), "imports up a floor (tests/test_imports.py, FLOORS):\n" + "\n".join(arrows_up(graph))


def test_an_import_up_a_floor_or_a_room_without_a_floor_is_found():
    floors = (("pkg.a",), ("pkg.b",))
    assert arrows_up({"pkg.b": {"pkg.a"}, "pkg.a": set()}, floors) == []
    assert arrows_up({"pkg.a.x": {"pkg.b.y"}, "pkg.b.y": set()}, floors) == ["pkg.a.x -> pkg.b.y"]
    assert arrows_up({"pkg.a": set(), "pkg.c": {"pkg.a"}}, floors) == ["pkg.c: no floor (add its room to FLOORS)"]


@pytest.mark.parametrize("graph, expected", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
    ({"a": {"b"}, "b": {"a"}, "c": {"a"}}, [["a", "b"]]),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"e"}, "e": {"d"}}, [["a", "b", "c"], ["d", "e"]]),
])
def test_cycles_are_the_strongly_connected_components(graph, expected):
    assert sorted(cycles(graph)) == expected
