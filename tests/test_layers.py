"""Packages are layers: each imports only itself and the packages below it, in one order.

Two views of the same tree, both checked: by dotted name (``curlnav.replay.table``: the package
names a reader and the import system see, with the ``package-dir`` mapping of pyproject.toml) and
by folder as the files lie (``replay/table.py``: what a tool that does not know the mapping
sees). An import that runs back up, or a circle between two packages or two modules, fails with
the file and line that makes it. A new package has to be placed in ``ORDER`` (CONTRIBUTING,
"Layers"; docs/guide/layout.md).
"""

from __future__ import annotations

import ast
import tomllib
from collections.abc import Callable
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
MAPPED = dict(SETUPTOOLS["package-dir"])  # curlnav.replay -> replay
#: bottom first: a package may import itself and the packages before it, nothing after
ORDER = ["proto", "files", "layout", "memory", "worlds", "sim", "config", "policy", "bus", "nav", "scheduler",
         "replay", "learner", "actor", "ros2", "evaluation", "builder", "run", "bench", "cli"]
#: narrower rules that stay: (importer, imported) -> the only module it may import there
EXTRA = {("actor", "learner"): "curlnav.learner.networks"}  # an actor runs the networks, never the learner
BARE = {name.split(".")[1] for name in MAPPED}  # `import replay` would follow the folder, not the package


@cache
def modules() -> dict[str, Path]:
    """Every module of the project: dotted name -> file (curlnav/ and every mapped folder)."""
    roots = {"curlnav": ROOT / "curlnav", **{name: ROOT / folder for name, folder in MAPPED.items()}}
    out = {}
    for package, folder in roots.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder).with_suffix("")
            if package == "curlnav" and rel.parts[0] in {name.split(".")[1] for name in MAPPED}:
                continue  # not there (a mapped package lives in its folder)
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join([package, *parts])] = path
    return out


def room_by_name(module: str) -> str | None:
    """``curlnav.replay.table`` -> ``replay``; ``curlnav.cli`` -> ``cli``; ``curlnav`` -> None (no room)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def room_by_folder(path: Path) -> str | None:
    """``replay/table.py`` -> ``replay``; ``curlnav/sim/env.py`` -> ``sim``; ``curlnav/cli.py`` ->
    ``cli``; ``curlnav/__init__.py`` -> None: the tree as the folders lie."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    if parts[0] != "curlnav":
        return parts[0]
    return None if parts[1:] == ("__init__",) else parts[1]


@cache
def imports(module: str) -> list[tuple[int, str]]:
    """(line, imported module) for every import in ``module`` (at import time, in functions, or
    for type checking); ``from a import b`` names ``a.b`` when that is a module."""
    path = modules()[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append((node.lineno, name))
            out += [(node.lineno, f"{name}.{alias.name}") for alias in node.names if f"{name}.{alias.name}" in modules()]
    return out


def target_module(name: str) -> str | None:
    """The project module an imported name resolves to (its longest known prefix), else None."""
    while name and name not in modules():
        name = name.rpartition(".")[0]
    return name or None


Room = Callable[[str], "str | None"]
VIEWS = {"by name": lambda module: room_by_name(module), "by folder": lambda module: room_by_folder(modules()[module])}


def edges(view: Room) -> dict[tuple[str, str], list[str]]:
    """(room a, room b) -> ["file:line imports target", ...] for every import from a into b != a."""
    out: dict[tuple[str, str], list[str]] = {}
    for module, path in modules().items():
        a = view(module)
        for line, name in imports(module):
            target = target_module(name)
            b = view(target) if target else None
            if a is None or b is None or a == b:
                continue
            out.setdefault((a, b), []).append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return out


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of more than one node (the circles)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


@pytest.mark.parametrize("view", VIEWS.values(), ids=VIEWS.keys())
def test_packages_import_only_packages_below_them(view):
    upward = []
    for (a, b), where in sorted(edges(view).items()):
        if a not in ORDER or b not in ORDER:
            continue  # test_every_package_is_in_the_order names it
        if ORDER.index(b) > ORDER.index(a):
            upward += [f"{a} -> {b} (above it): {w}" for w in where]
        elif (a, b) in EXTRA:
            upward += [f"{a} may import only {EXTRA[a, b]} of {b}: {w}" for w in where
                       if target_module(w.rsplit(" ", 1)[1]) != EXTRA[a, b]]
    assert not upward, "\n".join(upward)


@pytest.mark.parametrize("view", VIEWS.values(), ids=VIEWS.keys())
def test_no_circle_between_packages(view):
    graph: dict[str, set[str]] = {}
    for a, b in edges(view):
        graph.setdefault(a, set()).add(b)
    assert strongly_connected(graph) == []


def test_no_bare_import_of_a_mapped_folder():
    """``import replay`` works from the repository root only, and names a folder, not the package."""
    bare = [f"{path.relative_to(ROOT)}:{line} imports {name}" for module, path in modules().items()
            for line, name in imports(module) if name.split(".")[0] in BARE]
    assert not bare, "\n".join(bare)


def test_no_import_circle_between_modules():
    """A circle (a imports b imports a, at import time or for type checking) makes a module
    impossible to read or move alone; `sim/env.py` <-> `sim/render.py` was one. A package's face
    importing its own submodules is no circle a reader trips on."""
    graph = {module: set() for module in modules()}
    for module in modules():
        for _, name in imports(module):
            target = target_module(name)
            if target and target != module and not target.startswith(module + ".") \
                    and not (modules()[target].name == "__init__.py" and module.startswith(target + ".")):
                graph[module].add(target)
    assert strongly_connected(graph) == []


def test_every_package_is_in_the_order():
    rooms = {room for view in VIEWS.values() for room in map(view, modules())} - {None}
    assert sorted(rooms - set(ORDER)) == [], "place each new package in ORDER (CONTRIBUTING, Layers)"
    top = {p for p in SETUPTOOLS["packages"] if p.count(".") == 1}  # sub-packages: test_sub_packages_are_listed
    assert sorted(top) == sorted(f"curlnav.{r}" for r in rooms
                                                                       if (ROOT / "curlnav" / r).is_dir()
                                                                       or f"curlnav.{r}" in MAPPED)


def test_package_faces_name_what_they_offer():
    """Every package declares ``__all__``, and every name in it is there: bound in the
    ``__init__`` (or served by its ``__getattr__``) or a submodule. A face that imports nothing
    names every submodule."""
    wrong = []
    for module, path in modules().items():
        if path.name != "__init__.py" or module == "curlnav":
            continue
        tree = ast.parse(path.read_text())
        bound = set()
        declared = None
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
                bound.add(node.name)
                if node.name == "__getattr__":  # lazy names: the strings it compares against
                    bound |= {c.value for c in ast.walk(node) if isinstance(c, ast.Constant) and isinstance(c.value, str)}
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                bound |= {(alias.asname or alias.name).split(".")[0] for alias in node.names}
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for t in targets:
                    if isinstance(t, ast.Name):
                        bound.add(t.id)
                        if t.id == "__all__":
                            try:
                                declared = ast.literal_eval(node.value)
                            except ValueError:  # computed (ros2: sorted(_WHERE)): present, not checked here
                                declared = []
        if declared is None:
            wrong.append(f"{path.relative_to(ROOT)} declares no __all__")
            continue
        for name in declared:
            if name not in bound and f"{module}.{name}" not in modules():
                wrong.append(f"{path.relative_to(ROOT)}: __all__ names {name!r}, which it does not offer")
        if not any(isinstance(node, (ast.Import, ast.ImportFrom)) for node in tree.body):
            submodules = {m.rpartition(".")[2] for m in modules() if m.rpartition(".")[0] == module}
            missing = sorted(n for n in submodules - set(declared) if not n.startswith("_"))
            if missing:
                wrong.append(f"{path.relative_to(ROOT)}: __all__ leaves out {', '.join(missing)}")
    assert not wrong, "\n".join(wrong)


#: the navigation stack's rooms (``curlnav.nav.ROOM``), bottom first: the roles' shared parts, the
#: roles in the order they wrap one another's inputs, then the stack, its builder and the stack a network
#: trains inside; the package's face (``curlnav.nav``) sits on top
NAV_ORDER = ["registry", "geometry", "roles", "progress", "perception", "safety", "global_planners", "controllers",
             "recovery", "stack", "build", "training"]


def nav_room(module: str) -> str | None:
    """``curlnav.nav.safety.shield`` -> ``safety``; ``curlnav.nav`` -> ``face``; outside -> None."""
    parts = module.split(".")
    if parts[:2] != ["curlnav", "nav"]:
        return None
    return parts[2] if len(parts) > 2 else "face"


def test_no_private_name_is_imported_across_modules():
    """``from a import _b``: a name its module keeps to itself, used elsewhere (the rescue took a
    private of the local planners once); a shared helper is public where it lives."""
    private = []
    for module, path in modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module != "__future__":
                private += [f"{path.relative_to(ROOT)}:{node.lineno} imports {alias.name} from {node.module}"
                            for alias in node.names if alias.name.startswith("_") and not alias.name.startswith("__")]
    assert not private, "\n".join(private)


def test_no_package_holds_more_than_a_dozen_modules():
    """A package a reader can take in: at most 12 modules besides its face; more is split by concern."""
    count: dict[str, int] = {}
    for module, path in modules().items():
        if path.name != "__init__.py":
            package = module.rpartition(".")[0]
            count[package] = count.get(package, 0) + 1
    assert {p: n for p, n in count.items() if n > 12} == {}


def test_sub_packages_are_listed_for_installation():
    """Every package folder is in pyproject.toml's packages: a regular install (the images') has it."""
    folders = {m for m, path in modules().items() if path.name == "__init__.py"}
    assert sorted(folders - set(SETUPTOOLS["packages"])) == []


#: ``curlnav.worlds`` inside, bottom first: its sub-packages, then the modules at its top (``top``:
#: the family registry, levels, distributions, the resolver, the commands); its face sits above them all
WORLDS_ORDER = ["core", "difficulty", "procedural", "real", "barn_challenge", "top"]


def worlds_room(module: str) -> str | None:
    """``curlnav.worlds.core.world`` -> ``core``; ``curlnav.worlds.builtin`` -> ``top``;
    ``curlnav.worlds`` -> ``face``; outside -> None."""
    parts = module.split(".")
    if parts[:2] != ["curlnav", "worlds"]:
        return None
    if len(parts) == 2:
        return "face"
    return parts[2] if (ROOT / "curlnav" / "worlds" / parts[2]).is_dir() else "top"


#: the packages layered inside: their rooms bottom first, and the room of a module (None: outside)
INNER = {"curlnav.nav": (NAV_ORDER, nav_room), "curlnav.worlds": (WORLDS_ORDER, worlds_room)}


@pytest.mark.parametrize("package", INNER)
def test_inside_a_layered_package_each_room_imports_only_rooms_below_it(package):
    """Inside ``curlnav.nav`` a role imports only the rooms below it (a safety layer never imports a
    controller); inside ``curlnav.worlds`` the world model imports no metric and a generator nothing
    of the real maps or the BARN Challenge. Nothing imports the package's face from inside, no two
    rooms make a circle, and every room is placed in the order."""
    order, room = INNER[package]
    upward, graph = [], {}
    for module, path in modules().items():
        a = room(module)
        if a is None:
            continue
        for line, name in imports(module):
            target = target_module(name)
            b = room(target) if target else None
            if b is None or a == b:
                continue
            graph.setdefault(a, set()).add(b)
            if b == "face" or (a != "face" and order.index(b) > order.index(a)):
                upward.append(f"{a} -> {b} (above it): {path.relative_to(ROOT)}:{line} imports {name}")
    assert not upward, "\n".join(upward)
    assert strongly_connected(graph) == []
    rooms = {room(m) for m in modules()} - {None, "face"}
    assert sorted(rooms - set(order)) == [], f"place each new room of {package} in its order"
