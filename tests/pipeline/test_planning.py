"""Run planning from the config (flylib.pipeline.planning): the config rig built from
its tables alone, the params each stage's artifact should carry, and provenance
taking those params rather than a config."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flylib.camera.rig import CameraGroup
from flylib.config import Config
from flylib.interop.anipose import write_anipose_toml
from flylib.pipeline.inputs import RigSpec, stage_params
from flylib.pipeline.planning import calibration_inputs, config_rig, params_of
from flylib.provenance import PARAMS_KEY, params_hash, stage_provenance


def _assert_same_rig(a: CameraGroup, b: CameraGroup) -> None:
    assert a.names == b.names
    for name in ("rvecs", "tvecs", "intrs", "dists"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _tracked(rig: RigSpec) -> dict:
    """The rig as a job gets it: the params' canonical JSON, keys sorted."""
    return json.loads(json.dumps(rig.params(), sort_keys=True))


@pytest.fixture(scope="module")
def default() -> Config:
    return Config.default()


def test_the_config_rig_is_the_orbit_rig_of_the_cameras_table(default):
    sizes = {v: (480, 960) for v in default.view_names()}
    rig = config_rig(default, sizes)
    defaults, specs = default.camera_table()
    _assert_same_rig(rig, CameraGroup.from_table(specs, defaults, sizes))
    # the seed's CameraGroup.from_config asks the config for its table
    _assert_same_rig(rig, CameraGroup.from_config(default, image_sizes=sizes))


def test_a_job_rebuilds_the_rig_in_view_order_from_the_sorted_params(default):
    data = default.data
    # views whose names do not sort in rig order, so sorted params would scramble them
    renamed = {f"{i}_{v}" if i % 2 else f"z{i}_{v}": v for i, v in enumerate(default.view_names())}
    cameras = {"defaults": data["cameras"]["defaults"]}
    cameras.update({new: data["cameras"][old] for new, old in renamed.items()})
    output_points = {new: data["pose2d"]["output_points"][old] for new, old in renamed.items()}
    config = Config.from_dict(
        {**data, "cameras": cameras, "pose2d": {**data["pose2d"], "output_points": output_points}}
    )
    views = list(renamed)
    assert views != sorted(views)
    sizes = {v: (480, 960) for v in views}
    rig = RigSpec.from_params(_tracked(RigSpec.from_config(config))).camera_group(sizes)
    assert rig.names == views
    _assert_same_rig(rig, config_rig(config, sizes))


def test_a_calibration_rig_without_a_cameras_table_keeps_the_output_points_views(default, tmp_path):
    sizes = {v: (480, 960) for v in default.view_names()}
    write_anipose_toml(config_rig(default, sizes), tmp_path / "calibration.toml", sizes)
    data = {k: v for k, v in default.data.items() if k != "cameras"}
    config = Config(
        {**data, "calibration": {"file": "calibration.toml"}}, source=tmp_path / "config.yaml"
    )
    views = config.view_names()
    assert views == list(default.data["pose2d"]["output_points"])
    spec = RigSpec.from_config(config)
    assert spec.calibration is not None and not spec.cameras
    # a relative calibration path resolves against the config's folder, for the job too
    job = RigSpec.from_params(_tracked(spec), spec.config_dir)
    rig = job.camera_group(sizes)
    assert rig.names == views
    _assert_same_rig(rig, config_rig(config, sizes))
    # the file's cameras are the default rig's (the TOML pads distortion to 5 zeros)
    fly = np.random.default_rng(0).uniform(-3, 3, size=(50, 3))
    np.testing.assert_allclose(
        rig.project(fly), config_rig(default, sizes).subset(views).project(fly), atol=1e-9
    )
    assert calibration_inputs(config) == [tmp_path / "calibration.toml"]
    assert calibration_inputs(default) == []


def test_params_of_gives_each_stages_tracked_params_or_none_for_a_stage_not_run(default):
    everything, run = params_of(default), params_of(default, run_only=True)
    flags = default.stage_flags()
    assert not flags["pictorial_structures"] and flags["triangulation"]
    assert run("pictorial_structures") is None
    assert everything("pictorial_structures") == stage_params(default, "pictorial_structures")
    for stage in ("triangulation", "assemble"):
        assert run(stage) == everything(stage) == stage_params(default, stage)


def test_stage_provenance_hashes_the_params_and_refuses_a_config(default):
    params = stage_params(default, "triangulation")
    meta = stage_provenance(params, "triangulation")
    assert meta[PARAMS_KEY] == params_hash(stage_params(default, "triangulation"))
    with pytest.raises(TypeError, match=r"stage_params\(config, 'triangulation'\)"):
        stage_provenance(default, "triangulation")
