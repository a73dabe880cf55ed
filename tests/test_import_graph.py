"""flylib's import graph: no cycles, and no module imports a higher layer.

Every module under ``src/flylib`` is parsed with :mod:`ast`; every ``import`` and
``from ... import`` counts, inside functions included (a deferred import still ties
the two modules together), except those under ``if TYPE_CHECKING:``. Relative imports
are resolved; ``from pkg import name`` is an edge to ``pkg.name`` when that is a
module, else to ``pkg``; a name that ``flylib``'s stub (``__init__.pyi``) exports
lazily is an edge to the module the stub takes it from.

The layers, lowest first (:data:`LAYERS`); a module may import its own layer or any
below it:

0. foundation -- errors, paths, resources, locking, the stage registry; the package root
   (lazy exports only)
1. primitives -- camera models and geometry, the skeleton, frame readers
2. config -- :class:`~flylib.config.Config` and its validation (NWB metadata checks)
3. recordings -- which directories hold footage, and the demo directory's layout
4. algorithms -- detection, bundle adjustment, pictorial structures, triangulation,
   refinement, the held-out-view accuracy, kinematics, rendering
5. data -- stage artifacts and results, provenance, suspects, corrections, file
   formats of other tools, the demo generator
6. stages -- the stage functions the workflow runs, preflight checks, run summaries
7. applications -- the command line and the review GUI
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

#: ``(layer name, module prefixes)``, lowest first. A prefix names a module and all
#: its submodules; the most specific prefix wins. The root ``flylib`` matches only
#: itself.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "foundation",
        (
            "flylib",
            "flylib.errors",
            "flylib.paths",
            "flylib.resources",
            "flylib.locking",
            "flylib.stages",
        ),
    ),
    (
        "primitives",
        (
            "flylib.alignment",
            "flylib.camera",
            "flylib.skeleton",
            "flylib.handedness",
            "flylib.io",
        ),
    ),
    ("config", ("flylib.config",)),
    ("recordings", ("flylib.recordings", "flylib.sessions")),
    (
        "algorithms",
        (
            "flylib.pose2d",
            "flylib.bundle_adjustment",
            "flylib.pictorial",
            "flylib.triangulation",
            "flylib.refinement",
            "flylib.accuracy",
            "flylib.kinematics",
            "flylib.neuromechfly",
            "flylib.visualization",
        ),
    ),
    (
        "data",
        (
            "flylib.results",
            "flylib.provenance",
            "flylib.suspects",
            "flylib.corrections",
            "flylib.interop",
            "flylib.demo",
            "flylib.pose2d.stream",
        ),
    ),
    (
        "stages",
        (
            "flylib.pipeline",
            "flylib.run_summary",
        ),
    ),
    ("applications", ("flylib.cli", "flylib.doctor", "flylib.gui", "flylib.starter")),
)


# -- the graph -------------------------------------------------------------------


def find_modules(src: Path, package: str) -> dict[str, Path]:
    """Every module of ``package`` under ``src``: dotted name -> file (``__init__.py`` for a package)."""
    modules = {}
    for path in sorted((src / package).rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(tree: ast.AST, *, type_checking: bool = False):
    """Import nodes anywhere in ``tree`` (function bodies too), except ``if TYPE_CHECKING:``
    bodies unless ``type_checking``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If) and _is_type_checking(node) and not type_checking:
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def _owner(name: str, modules: dict[str, Path]) -> str | None:
    """The module ``name`` refers to: itself, else its closest enclosing module."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _lazy_exports(src: Path, package: str) -> dict[str, str]:
    """``name -> module`` of the names the package stub ``__init__.pyi`` exports lazily."""
    stub = src / package / "__init__.pyi"
    if not stub.is_file():
        return {}
    exports = {}
    for node in _import_nodes(ast.parse(stub.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
            for alias in node.names:
                exports[alias.asname or alias.name] = f"{package}.{node.module}"
    return exports


def import_graph(
    src: Path, package: str, *, type_checking: bool = False
) -> dict[str, dict[str, int]]:
    """``module -> {imported module of the package: line of the first such import}``
    (``type_checking``: the imports under ``if TYPE_CHECKING:`` too)."""
    modules = find_modules(src, package)
    lazy = _lazy_exports(src, package)
    graph: dict[str, dict[str, int]] = {}
    for name, path in modules.items():
        here = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges: dict[str, int] = {}
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in _import_nodes(tree, type_checking=type_checking):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                if node.level:
                    base = here.split(".")[: len(here.split(".")) - node.level + 1]
                    origin = ".".join(base + ([node.module] if node.module else []))
                else:
                    origin = node.module or ""
                targets = []
                for alias in node.names:
                    if origin == package and alias.name in lazy:
                        targets.append(lazy[alias.name])
                    elif f"{origin}.{alias.name}" in modules:
                        targets.append(f"{origin}.{alias.name}")
                    else:
                        targets.append(origin)
            for target in targets:
                owner = _owner(target, modules) if target.split(".")[0] == package else None
                if owner is not None and owner != name:
                    edges.setdefault(owner, node.lineno)
        graph[name] = edges
    return graph


def find_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """One cycle ``[a, b, ..., a]`` through each strongly connected component of two or more modules."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)

    cycles = []
    for component in components:
        members = set(component)
        start = component[0]
        parent: dict[str, str] = {}
        queue = [start]
        while queue:  # shortest path from start back to start inside the component
            v = queue.pop(0)
            if start in graph[v]:
                path = [start, v]
                while v != start:
                    v = parent[v]
                    path.append(v)
                cycles.append(path[::-1])
                break
            for w in sorted(graph[v]):
                if w in members and w not in parent and w != start:
                    parent[w] = v
                    queue.append(w)
    return cycles


def describe(cycle: list[str], graph: dict[str, dict[str, int]]) -> str:
    """``a -> b (a's line) -> ... -> a``."""
    steps = [cycle[0]] + [f"{b} (line {graph[a][b]} of {a})" for a, b in zip(cycle, cycle[1:])]
    return " -> ".join(steps)


def layer_of(module: str) -> int | None:
    """Index in :data:`LAYERS` of ``module``'s most specific prefix (``None``: unassigned)."""
    best = None
    for level, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            matches = module == prefix or (prefix != "flylib" and module.startswith(prefix + "."))
            if matches and (best is None or len(prefix) > len(best[1])):
                best = (level, prefix)
    return None if best is None else best[0]


# -- flylib ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def graph() -> dict[str, dict[str, int]]:
    return import_graph(SRC, "flylib")


def test_flylib_has_no_import_cycles(graph):
    cycles = find_cycles(graph)
    assert not cycles, "import cycles among flylib's modules:\n" + "\n".join(
        describe(c, graph) for c in cycles
    )


def test_no_import_cycle_even_through_type_checking_imports():
    # an annotation-only import still ties two modules' meanings together (cameras.py
    # and skeleton.py once named the Config that builds them)
    graph = import_graph(SRC, "flylib", type_checking=True)
    cycles = find_cycles(graph)
    assert not cycles, "import cycles among flylib's modules, TYPE_CHECKING included:\n" + (
        "\n".join(describe(c, graph) for c in cycles)
    )


def test_every_module_has_a_layer(graph):
    missing = sorted(m for m in graph if layer_of(m) is None)
    assert not missing, (
        f"modules without a layer: {missing}; add them to LAYERS in {Path(__file__).name}"
    )


def test_no_module_imports_a_higher_layer(graph):
    upward = [
        f"{a} ({LAYERS[layer_of(a)][0]}) imports {b} ({LAYERS[layer_of(b)][0]}) at line {line}"
        for a, edges in sorted(graph.items())
        for b, line in edges.items()
        if layer_of(a) is not None and layer_of(b) is not None and layer_of(b) > layer_of(a)
    ]
    assert not upward, "imports of a higher layer:\n" + "\n".join(upward)


# -- the checker itself ------------------------------------------------------------


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = tmp_path / "pkg" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return tmp_path


def test_a_cycle_through_a_function_body_and_a_relative_import_is_found(tmp_path):
    src = _package(
        tmp_path,
        {
            "__init__.py": "",
            "a.py": "from .sub import b\n",
            "sub/__init__.py": "",
            "sub/b.py": "def f():\n    import pkg.c\n",
            "c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import d\nelse:\n    from .a import x\n",
            "d.py": "from .c import y\n",
        },
    )
    graph = import_graph(src, "pkg")
    assert graph["pkg.a"] == {"pkg.sub.b": 1}
    assert graph["pkg.c"] == {"pkg.a": 5}  # the TYPE_CHECKING branch does not count
    typed = import_graph(src, "pkg", type_checking=True)
    assert typed["pkg.c"] == {"pkg.d": 3, "pkg.a": 5}
    assert typed["pkg.d"] == {"pkg.c": 1}
    cycles = find_cycles(graph)
    assert cycles == [["pkg.a", "pkg.sub.b", "pkg.c", "pkg.a"]]
    assert describe(cycles[0], graph) == (
        "pkg.a -> pkg.sub.b (line 1 of pkg.a) -> pkg.c (line 2 of pkg.sub.b) -> pkg.a (line 5 of pkg.c)"
    )


def test_names_from_a_package_and_its_lazy_stub_point_at_their_modules(tmp_path):
    src = _package(
        tmp_path,
        {
            "__init__.py": "",
            "__init__.pyi": "from .core import Thing as Thing\n",
            "core.py": "def f():\n    from pkg import Thing, helpers\n",
            "helpers.py": "from . import __version__\nfrom pkg import Thing\n",
        },
    )
    graph = import_graph(src, "pkg")
    assert graph["pkg.helpers"] == {"pkg": 1, "pkg.core": 2}
    assert graph["pkg.core"] == {"pkg.helpers": 2}
    assert find_cycles(graph) == [["pkg.core", "pkg.helpers", "pkg.core"]]


def test_layers_take_the_most_specific_prefix():
    assert layer_of("flylib") == layer_of("flylib.errors") == 0
    assert layer_of("flylib.pose2d.inference") == 4 < layer_of("flylib.pose2d.stream") == 5
    assert layer_of("flylib.triangulation.kernels") == 4
    assert layer_of("flylib.not_a_module") is None


# -- privacy and lazy imports ----------------------------------------------------------


def private_imports(root: Path) -> list[str]:
    """``from <flylib module> import _name`` anywhere under ``root``'s code folders: a
    name another module uses is public (no leading underscore)."""
    found = []
    for folder in ("src", "scripts", "tests", "benchmarks"):
        for path in sorted((root / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for node in ast.walk(tree):
                if not isinstance(node, ast.ImportFrom):
                    continue
                ours = node.level > 0 or (node.module or "").split(".")[0] in ("flylib", "_cli")
                for alias in node.names if ours else ():
                    if alias.name.startswith("_") and not alias.name.startswith("__"):
                        found.append(f"{path.relative_to(root)}:{node.lineno} {alias.name}")
    return found


def test_no_module_imports_another_modules_private_name():
    found = private_imports(SRC.parent)
    assert not found, "make these names public: " + ", ".join(found)


def test_one_lazy_import_mechanism():
    """A package defers its heavy imports only through ``lazy_loader.attach_stub`` over
    its ``__init__.pyi``: no hand-written module ``__getattr__``."""
    hand_written = []
    for path in sorted((SRC / "flylib").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
                hand_written.append(str(path.relative_to(SRC)))
    assert not hand_written, f"module __getattr__ written by hand in {hand_written}"
    stubs = sorted(p.parent.name for p in (SRC / "flylib").rglob("__init__.pyi"))
    for package in stubs:
        init = (SRC / "flylib" / package / "__init__.py") if package != "flylib" else None
        init = init or SRC / "flylib" / "__init__.py"
        assert "attach_stub" in init.read_text(encoding="utf-8"), init


def test_the_privacy_check_sees_a_private_import(tmp_path):
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "a.py").write_text(
        "from .b import _helper\nfrom flylib.c import __version__\n"
    )
    assert private_imports(tmp_path) == ["src/a.py:1 _helper"]
