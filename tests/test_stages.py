"""The stage registry (flylib.stages): every stage table is derived from its records,
and holds for each stage what the tables held when they were written by hand."""

from __future__ import annotations

import importlib
import subprocess
import sys
from collections.abc import Mapping

import pytest

from flylib import stages
from flylib.config import PARAM_STAGES, STAGE_DEFAULTS, STAGES, Config
from flylib.pipeline.inputs import StageInputs, inputs_class
from flylib.results import ARTIFACTS, STAGE_GROUPS

# The hand-written tables the registry replaced (as they stood at tag base33).
OLD_STAGES = (
    "pose2d",
    "bundle_adjustment",
    "pictorial_structures",
    "triangulation",
    "refinement",
    "kinematics",
    "neuromechfly",
    "visualization",
)
OLD_STAGE_DEFAULTS = {
    "pose2d": True,
    "bundle_adjustment": True,
    "pictorial_structures": False,
    "triangulation": True,
    "refinement": True,
    "kinematics": True,
    "neuromechfly": False,
    "visualization": True,
}
OLD_PARAM_STAGES = (
    "pose2d",
    "bundle_adjustment",
    "pictorial_structures",
    "triangulation",
    "refinement",
    "assemble",
    "kinematics",
    "neuromechfly",
    "visualization",
)
OLD_ARTIFACTS = {
    "pose2d": "pose2d.h5",
    "bundle_adjustment": "bundle_adjustment.h5",
    "pictorial_structures": "pictorial_structures.h5",
    "triangulation": "triangulation.h5",
    "refinement": "refinement.h5",
}
OLD_STAGE_GROUPS = (
    "pose2d",
    "bundle_adjustment",
    "pictorial_structures",
    "triangulation",
    "refinement",
)
OLD_FIXED_MB = {
    "bundle_adjustment": 380,
    "triangulation": 110,
    "refinement": 410,
    "assemble": 160,
    "kinematics": 130,
}
OLD_PER_MILLION_MB = {
    "bundle_adjustment": 30,
    "triangulation": 120,
    "refinement": 140,
    "assemble": 130,
    "kinematics": 105,
}
OLD_CHECK = {
    "bundle_adjustment": "check its 2D (are the views' points of one fly, in raw-frame pixels?) "
    "and the starting rig (cameras, calibration.file), or set "
    "pipeline.do_bundle_adjustment: false",
    "pictorial_structures": "check the detector's 2D and the rig, or set "
    "pipeline.do_pictorial_structures: false",
    "triangulation": "check its 2D (pose2d, corrections) and the rig (bundle adjustment's "
    "result, cameras, calibration.file)",
    "refinement": "check triangulation's 3D (flylib inspect) and the refinement settings, or "
    "set pipeline.do_refinement: false",
    "kinematics": "check the 3D in results.h5 (flylib inspect), or set "
    "pipeline.do_kinematics: false",
}


def _old_flags(pipeline: dict) -> dict[str, bool]:
    """Config.stage_flags as written by hand before the registry."""
    flags = {s: bool(pipeline.get(f"do_{s}", OLD_STAGE_DEFAULTS[s])) for s in OLD_STAGES}
    flags["refinement"] &= flags["triangulation"]
    flags["kinematics"] &= flags["triangulation"] or flags["pictorial_structures"]
    flags["neuromechfly"] &= flags["triangulation"] or flags["pictorial_structures"]
    return flags


def _old(table, old):
    """``table`` restricted to the stages ``old`` names (a stage added since is no
    change to the old ones), in its own order."""
    if isinstance(table, Mapping):
        return {k: v for k, v in table.items() if k in old}
    return tuple(k for k in table if k in old)


def test_derived_tables_keep_the_old_tables():
    assert _old(STAGES, OLD_STAGES) == OLD_STAGES
    assert list(_old(STAGE_DEFAULTS, OLD_STAGE_DEFAULTS).items()) == list(
        OLD_STAGE_DEFAULTS.items()
    )
    assert _old(PARAM_STAGES, OLD_PARAM_STAGES) == OLD_PARAM_STAGES
    assert list(_old(ARTIFACTS, OLD_ARTIFACTS).items()) == list(OLD_ARTIFACTS.items())
    assert _old(STAGE_GROUPS, OLD_STAGE_GROUPS) == OLD_STAGE_GROUPS
    fixed = {s.name: s.memory[0] for s in stages.REGISTRY if s.memory}
    per_million = {s.name: s.memory[1] for s in stages.REGISTRY if s.memory}
    assert _old(fixed, OLD_FIXED_MB) == OLD_FIXED_MB
    assert _old(per_million, OLD_PER_MILLION_MB) == OLD_PER_MILLION_MB
    assert _old({s.name: s.hint for s in stages.REGISTRY if s.hint}, OLD_CHECK) == OLD_CHECK


@pytest.mark.parametrize("bits", range(1 << 4))
def test_stage_flags_keep_the_old_dependencies(bits):
    toggled = ("pose2d", "pictorial_structures", "triangulation", "refinement")
    pipeline = {f"do_{s}": bool(bits >> i & 1) for i, s in enumerate(toggled)}
    pipeline["do_neuromechfly"] = True
    flags = Config.from_dict({"pipeline": pipeline}).stage_flags()
    assert _old(flags, OLD_STAGE_DEFAULTS) == _old_flags(pipeline)


@pytest.mark.parametrize("stage", stages.REGISTRY, ids=lambda s: s.name)
def test_each_home_defines_its_run_function_and_a_registered_inputs_class(stage):
    home = importlib.import_module(stage.home)
    assert stage.run_function() is getattr(home, f"run_{stage.name}")
    assert stages.run_function(stage.name) is stage.run_function()
    cls = stage.inputs_class()
    assert issubclass(cls, StageInputs) and cls.STAGE == stage.name
    assert inputs_class(stage.name) is cls
    assert getattr(home, cls.__name__) is cls


def test_upstream_stages_exist_and_run_earlier():
    order = [s.name for s in stages.REGISTRY]
    assert len(set(order)) == len(order)
    for index, stage in enumerate(stages.REGISTRY):
        assert set(stage.after) <= set(order[:index]), (stage.name, stage.after)
        for upstream in stage.needs_one_of:
            assert upstream in order[:index], (stage.name, upstream)
            assert stages.by_name(upstream).toggled  # an always-on stage is no condition


def test_unknown_stages_are_refused():
    with pytest.raises(ValueError, match="unknown stage 'pose3d'"):
        stages.by_name("pose3d")

    class Stray(StageInputs):
        STAGE = "pose3d"

    with pytest.raises(ValueError, match="unknown stage 'pose3d'"):
        stages.register(Stray)


def test_importing_the_registry_imports_no_stage_home():
    code = (
        "import sys, flylib.stages, flylib.config, flylib.results; "
        "print(sorted(m for m in sys.modules if m.startswith('flylib.pipeline') "
        "or m.split('.')[0] in ('jax', 'torch')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_run_order_follows_after_and_a_cycle_is_named(tmp_path, monkeypatch):
    homes = tmp_path / "fake_homes"
    homes.mkdir()
    (homes / "__init__.py").write_text("")

    def home(name: str, after: tuple[str, ...]) -> None:
        record = f"RECORD = Stage({name!r}, default_on=True, after={after!r})"
        (homes / f"{name}.py").write_text(f"from flylib.stages import Stage\n\n{record}\n")
        sys.modules.pop(f"fake_homes.{name}", None)

    for name, after in (("b", ("a",)), ("a", ()), ("c", ("a",)), ("d", ("b", "c"))):
        home(name, after)
    (homes / "helper.py").write_text("RECORD = 'not a stage'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(stages, "_HOMES", "fake_homes")
    assert [s.name for s in stages.registry.__wrapped__()] == ["a", "b", "c", "d"]
    home("a", ("d",))
    with pytest.raises(ValueError, match="stages a, b, c, d: their 'after'"):
        stages.registry.__wrapped__()
