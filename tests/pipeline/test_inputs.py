"""Each stage's inputs object (flylib.pipeline.inputs): its params are exactly what the
stage's rule tracked before the inputs objects existed, and a job rebuilds the same
object from those params, so a stage reads only what its rule tracks.

``tests/data/stage_params_golden.json`` was written by the former
``Config.stage_params`` (the one statement of each stage's params until the inputs
objects replaced it) on the default config and fourteen variants of it: the
rig from bundle adjustment or the config, pictorial structures on and off, each
triangulation method, an import spec, no skeleton table, a calibration file, ...
Matching it keeps every artifact's ``params_sha256`` and so every existing result
valid across the change.
"""

from __future__ import annotations

import copy
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from flylib.config import PARAM_STAGES, Config
from flylib.pipeline.inputs import inputs_class, stage_inputs, stage_params
from flylib.pipeline.planning import config_rig

GOLDEN = json.loads(
    (Path(__file__).resolve().parents[1] / "data" / "stage_params_golden.json").read_text()
)


def _apply(base: dict, edits: list) -> dict:
    data = copy.deepcopy(base)
    for path, value in edits:
        node = data
        *parents, last = path.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        if value is None and path == "skeleton":
            node.pop(last, None)
        else:
            node[last] = value
    return data


@pytest.fixture(scope="module")
def configs() -> dict[str, Config]:
    return {
        name: Config.from_dict(_apply(GOLDEN["base"], variant["edits"]))
        for name, variant in GOLDEN["variants"].items()
    }


@pytest.mark.parametrize("stage", PARAM_STAGES)
def test_a_stages_params_are_what_its_rule_tracked_before(configs, stage):
    for name, config in configs.items():
        expected = GOLDEN["variants"][name]["params"][stage]
        assert stage_params(config, stage) == expected, name


@pytest.mark.parametrize("stage", PARAM_STAGES)
def test_a_job_rebuilds_the_same_inputs_from_the_tracked_params(configs, stage):
    cls = inputs_class(stage)
    for name, config in configs.items():
        inputs = stage_inputs(config, stage)
        params = json.loads(json.dumps(inputs.canonical_params()))
        rebuilt = cls.from_params(params, inputs.runtime_options)
        assert rebuilt == inputs, name
        assert pickle.loads(pickle.dumps(inputs)) == inputs, name


def test_a_rig_rebuilt_from_the_tracked_params_keeps_the_configs_view_order():
    # the params JSON sorts the cameras table's keys; the V axis must stay the config's
    from flylib.pipeline.inputs import RigSpec

    config = Config.default()
    views = config.view_names()
    assert views != sorted(views)
    tracked = json.loads(json.dumps(RigSpec.from_config(config).params(), sort_keys=True))
    sizes = {view: (480, 960) for view in views}
    rebuilt = RigSpec.from_params(tracked).camera_group(sizes)
    assert list(rebuilt.names) == views
    np.testing.assert_array_equal(rebuilt.tvecs, config_rig(config, sizes).tvecs)


def test_a_jobs_rig_keeps_the_configs_camera_order(configs):
    # canonical params sort the cameras table by name; the rig a job builds must still
    # put its cameras in the views' order (the V axis of every 2D array)
    config = configs["ba_off"]  # with bundle adjustment off every later stage holds the rig
    sizes = {view: (480, 960) for view in config.view_names()}
    checked = []
    for stage in PARAM_STAGES:
        inputs = stage_inputs(config, stage)
        if getattr(inputs, "rig", None) is None:
            continue
        params = json.loads(json.dumps(inputs.canonical_params()))
        rebuilt = inputs_class(stage).from_params(params, inputs.runtime_options)
        assert list(rebuilt.rig.camera_group(sizes).names) == config.view_names(), stage
        checked.append(stage)
    assert set(checked) >= {"pictorial_structures", "triangulation", "refinement", "assemble"}


def test_a_knob_marked_track_default_false_enters_the_params_only_off_its_default():
    from dataclasses import dataclass

    from flylib.config.checks import integer, number, param, tracked_table
    from flylib.config.params import build_params

    @dataclass(frozen=True)
    class Knobs:
        old: float = param(1.0, number(0))
        new: int = param(3, integer(1), track_default=False)

    assert tracked_table(Knobs()) == {"old": 1.0}  # the hash of results made before `new`
    assert tracked_table(Knobs(new=4)) == {"old": 1.0, "new": 4}
    for knobs in (Knobs(), Knobs(new=4)):
        assert build_params(Knobs, tracked_table(knobs)) == knobs
