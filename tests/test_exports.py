"""flylib's top level: every name in the type stub resolves, and ``import flylib`` stays cheap."""

from __future__ import annotations

import ast
import fnmatch
import functools
import importlib
import inspect
import json
import pkgutil
import subprocess
import sys
import tomllib
import types
import typing
from pathlib import Path

import pytest

import flylib

REPO = Path(__file__).resolve().parents[1]
STUB = REPO / "src" / "flylib" / "__init__.pyi"


def stub_exports() -> dict[str, str]:
    """``name -> module`` of every ``from .module import name as name`` in the stub."""
    exports = {}
    for node in ast.parse(STUB.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.ImportFrom):
            assert node.level == 1, (
                f"line {node.lineno}: the stub imports only from flylib's own modules"
            )
            for alias in node.names:
                assert alias.asname == alias.name, (
                    f"line {node.lineno}: write {alias.name} as {alias.name}"
                )
                exports[alias.name] = f"flylib.{node.module}"
    return exports


def test_every_stub_name_resolves_to_its_modules_object():
    exports = stub_exports()
    assert len(exports) >= 89
    assert sorted(flylib.__all__) == sorted(exports)
    assert set(exports) <= set(dir(flylib))
    for name, module in exports.items():
        assert getattr(flylib, name) is getattr(importlib.import_module(module), name), name
    from flylib import CameraGroup, write_nwb  # noqa: F401  (the from-import form, a dotted module)


def test_unknown_names_are_attribute_errors():
    with pytest.raises(AttributeError, match="no_such_name"):
        flylib.no_such_name  # noqa: B018


def test_import_flylib_loads_no_heavy_module():
    heavy = ["jax", "torch", "h5py", "pandas", "scipy", "cv2", "av", "pynwb", "matplotlib"]
    code = f"import sys, flylib; print(__import__('json').dumps([m for m in {heavy!r} if m in sys.modules]))"
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        env={"PYTHONPATH": str(REPO / "src"), "PATH": ""},
    )
    assert json.loads(out.stdout) == []


def test_shapes_are_for_type_checkers_only():
    # jaxtyping costs ~130 ms at import: the annotated modules import it only under TYPE_CHECKING
    modules = [
        "flylib.camera.rig",
        "flylib.camera.model",
        "flylib.camera.jax_model",
        "flylib.triangulation",
        "flylib.pictorial",
        "flylib.interop",
        "flylib.pipeline.kinematics",
        "flylib.suspects",
        "flylib.corrections",
        "flylib.results",
        "flylib.bundle_adjustment",
        "flylib.bundle_adjustment.adjust",
        "flylib.bundle_adjustment.gauge",
        "flylib.bundle_adjustment.lm",
        "flylib.bundle_adjustment.messages",
        "flylib.bundle_adjustment.params",
        "flylib.bundle_adjustment.reseed",
        "flylib.bundle_adjustment.sampling",
        "flylib.bundle_adjustment.sequence",
        "flylib.bundle_adjustment.problem",
        "flylib.bundle_adjustment.unknowns",
        "flylib.pipeline.oneshot",
        "flylib.refinement.objective",
        "flylib.refinement.setup",
        "flylib.refinement.solver",
        "flylib.pose2d.decode",
        "flylib.visualization.summary",
    ]
    code = f"import sys; [__import__(m) for m in {modules!r}]; print('jaxtyping' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        env={"PYTHONPATH": str(REPO / "src"), "PATH": "", "FLYLIB_NO_JAX_CACHE": "1"},
    )
    assert out.stdout.strip() == "False"


@functools.cache
def type_checking_namespace(module_name: str) -> dict:
    """The module's globals plus what its ``if TYPE_CHECKING:`` blocks import: what a type checker sees."""
    module = sys.modules[module_name]
    namespace = dict(vars(module))
    for node in ast.parse(inspect.getsource(module)).body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            exec(
                compile(ast.Module(body=node.body, type_ignores=[]), module.__file__, "exec"),
                namespace,
            )
    return namespace


def annotated(obj) -> list:
    """``obj`` and, for a class, its own methods and properties (not inherited ones)."""
    if not inspect.isclass(obj):
        return [obj] if callable(obj) else []
    own = [
        types.SimpleNamespace(
            __annotations__=vars(obj).get("__annotations__", {}), __module__=obj.__module__
        )
    ]
    for member in vars(obj).values():
        member = getattr(member, "__func__", member)  # classmethod, staticmethod
        member = (
            getattr(member, "fget", None) or getattr(member, "func", None) or member
        )  # (cached) property
        if inspect.isfunction(member):
            own.append(member)
    return own


def test_annotations_of_every_public_name_evaluate():
    # Annotations are strings (shapes are for type checkers); evaluating each one in the
    # namespace a type checker sees catches an unimported name or a malformed shape.
    shapes = 0
    for name in stub_exports():
        for target in annotated(getattr(flylib, name)):
            hints = typing.get_type_hints(
                target, globalns=type_checking_namespace(target.__module__)
            )
            shapes += sum("jaxtyping" in repr(hint) for hint in hints.values())
    assert shapes >= 30


@functools.cache
def public_objects() -> list[tuple[str, object]]:
    """``(module.name, obj)`` of every public name defined in every flylib module.

    Modules are found by walking the package, not listed: a new module is covered too.
    """
    found = []
    for info in pkgutil.walk_packages(flylib.__path__, "flylib."):
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if not name.startswith("_") and getattr(obj, "__module__", None) == info.name:
                found.append((f"{info.name}.{name}", obj))
    return found


def test_annotations_of_every_module_evaluate():
    # The stub's names above, and every other public function, class and method of
    # every module (triangulation.methods, camera.model, interop, kinematics, ...).
    failures, shapes = [], 0
    for qualname, obj in public_objects():
        for target in annotated(obj):
            try:
                hints = typing.get_type_hints(
                    target, globalns=type_checking_namespace(target.__module__)
                )
            except Exception as exc:  # noqa: BLE001 - collect them all
                failures.append(
                    f"{qualname}.{getattr(target, '__name__', '')}: {type(exc).__name__}: {exc}"
                )
                continue
            shapes += sum("jaxtyping" in repr(hint) for hint in hints.values())
    assert not failures, "\n".join(failures)
    assert shapes >= 300


#: Parameters that are arrays wherever they appear in the public API.
ARRAY_PARAMETERS = frozenset(
    {
        "pts2d",
        "pts3d",
        "conf",
        "weights",
        "reproj_error",
        "rvecs",
        "tvecs",
        "intrs",
        "dists",
        "pmats",
        "heatmaps",
    }
)
#: Names that are not arrays where they appear (``pose2d.weights``: ``weights`` is a checkpoint).
NOT_ARRAYS = {"flylib.pose2d.weights.resolve_weights": {"weights"}}


def test_public_array_parameters_have_shapes():
    missing = []
    for _, obj in public_objects():
        for target in annotated(obj):
            if not inspect.isfunction(target) or target.__name__.startswith("_"):
                continue
            hints = typing.get_type_hints(
                target, globalns=type_checking_namespace(target.__module__)
            )
            exempt = NOT_ARRAYS.get(f"{target.__module__}.{target.__qualname__}", set())
            missing += [
                f"{target.__module__}.{target.__qualname__}({name})"
                for name in inspect.signature(target).parameters
                if name in ARRAY_PARAMETERS - exempt and "jaxtyping" not in repr(hints.get(name))
            ]
    assert not missing, f"array parameters without a jaxtyping shape: {missing}"


def test_the_stub_ships_in_the_wheel():
    package_data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]
    for name in (STUB.name, "py.typed"):
        assert any(fnmatch.fnmatch(name, pattern) for pattern in package_data["flylib"]), name
        assert (STUB.parent / name).is_file()
