"""A numerical stage that fails on a recording's data is one line.

The probe's case: a DeepFly3D pickle of uniform random points2d made bundle adjustment
raise ``LinAlgError: Eigenvalues did not converge`` as a traceback (after 196 s). Each
numerical stage's solver is replaced here by one raising what solvers raise on such
data, and the stage function (what the workflow's scripts call) must turn it into one
:class:`StageError` line naming the recording, the stage and what to check -- while
flylib's own errors and storage errors pass unchanged.
"""

from __future__ import annotations

import numpy as np
import pytest

from flylib.config import Config
from flylib.errors import OutputError, StageError
from flylib.interop.views import view_names
from flylib.pipeline.bundle_adjustment import run_bundle_adjustment
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.stage_helpers import run_inputs
from flylib.pipeline.triangulation import run_triangulation
from flylib.results import Pose2dData


@pytest.fixture(scope="module")
def config():
    return Config.default()


@pytest.fixture
def pose2d(tmp_path, config):
    """Uniform random 2D (the probe's incoherent input) as a pose2d artifact."""
    views = view_names(config)
    rng = np.random.default_rng(0)
    shape = (len(views), 3, len(config.skeleton().point_names))
    pts = np.stack([rng.uniform(0, 960, shape), rng.uniform(0, 480, shape)], axis=-1)
    path = tmp_path / "stages" / "pose2d.h5"
    path.parent.mkdir()
    Pose2dData(
        pts2d=pts,
        conf=np.ones(shape),
        view_names=views,
        image_sizes={v: (480, 960) for v in views},
    ).save(path, config.skeleton())
    return path


def _raise(exc):
    def solver(*args, **kwargs):
        raise exc

    return solver


def _one_line(err, recording, *fragments):
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{recording}: "), text
    for fragment in fragments:
        assert fragment in text, text
    return text


def test_bundle_adjustment_linalg_error_is_one_line(monkeypatch, config, pose2d, tmp_path):
    import flylib.bundle_adjustment as ba

    monkeypatch.setattr(
        ba,
        "bundle_adjust_sequence",
        _raise(np.linalg.LinAlgError("Eigenvalues did not converge")),
    )
    out = tmp_path / "stages" / "bundle_adjustment.h5"
    with pytest.raises(StageError) as err:
        run_bundle_adjustment(
            stage_inputs(config, "bundle_adjustment"), pose2d, out, recording_dir=tmp_path
        )
    text = _one_line(
        err,
        tmp_path,
        "bundle adjustment failed on this recording's data",
        "LinAlgError: Eigenvalues did not converge",
        "pipeline.do_bundle_adjustment: false",
    )
    assert isinstance(err.value.__cause__, np.linalg.LinAlgError), text
    assert not out.exists()


@pytest.mark.parametrize(
    "exc",
    [
        FloatingPointError("overflow"),
        ValueError("array must not contain infs or NaNs"),
        MemoryError(),
    ],
)
def test_triangulation_failures_are_one_line(monkeypatch, config, pose2d, tmp_path, exc):
    import flylib.triangulation as triangulation

    monkeypatch.setattr(triangulation, "reconstruct", _raise(exc))
    with pytest.raises(StageError) as err:
        run_triangulation(
            run_inputs(config, "triangulation"),
            pose2d,
            tmp_path / "stages" / "triangulation.h5",
            recording_dir=tmp_path,
        )
    _one_line(err, tmp_path, "triangulation failed", type(exc).__name__, "check its 2D")


def test_refinement_and_kinematics_failures_name_the_recording(monkeypatch, config, tmp_path):
    import flylib.pipeline.refinement as refinement
    from flylib.pipeline.inputs import stage_inputs
    from flylib.pipeline.kinematics import run_kinematics
    from flylib.results import PoseResult

    monkeypatch.setattr(refinement, "refinement_rig", _raise(ZeroDivisionError("float division")))
    with pytest.raises(StageError) as err:
        refinement.run_refinement(
            stage_inputs(config, "refinement"), "p.h5", "t.h5", "r.h5", recording_dir=tmp_path
        )
    _one_line(err, tmp_path, "refinement failed", "ZeroDivisionError", "do_refinement: false")
    monkeypatch.setattr(PoseResult, "load", _raise(np.linalg.LinAlgError("SVD")))
    with pytest.raises(StageError) as err:
        run_kinematics(stage_inputs(config, "kinematics"), tmp_path / "results.h5", tmp_path)
    _one_line(err, tmp_path / "results.h5", "kinematics failed", "do_kinematics: false")


@pytest.mark.parametrize(
    "exc", [OutputError("x: disk full"), PermissionError(13, "Permission denied")]
)
def test_flylib_and_storage_errors_pass_unchanged(monkeypatch, config, pose2d, tmp_path, exc):
    import flylib.bundle_adjustment as ba

    monkeypatch.setattr(ba, "bundle_adjust_sequence", _raise(exc))
    inputs = stage_inputs(config, "bundle_adjustment")
    with pytest.raises(type(exc)) as err:
        run_bundle_adjustment(inputs, pose2d, tmp_path / "ba.h5", recording_dir=tmp_path)
    assert err.value is exc


def test_a_stop_that_c_code_wrapped_is_reported_as_the_stop(monkeypatch, pose2d, tmp_path, capsys):
    """A stop signal's exception raised while h5py's Cython lock was held came back as
    ``SystemError: <cyfunction FastRLock.__exit__> returned a result with an exception
    set``; the stage's boundary turned it into "failed on this recording's data". The
    bundle-adjustment script, as a job runs it, reports the stop."""
    import signal
    import sys

    import flylib.bundle_adjustment as ba
    from flylib.paths import DEFAULT_CONFIG_PATH
    from tests.workflow_run import load_script

    script = load_script("bundle_adjustment")
    stopped = sys.modules["_cli"]._Stopped

    def stopped_in_c_code(*args, **kwargs):
        try:
            raise stopped(signal.SIGTERM)  # what the script's stop handler raises
        except stopped as stop:  # what CPython makes of it when C code returns with it
            raise SystemError(
                "<cyfunction FastRLock.__exit__> returned a result with an exception set"
            ) from stop

    monkeypatch.setattr(ba, "bundle_adjust_sequence", stopped_in_c_code)
    out = tmp_path / "stages" / "bundle_adjustment.h5"
    status = script.main(
        ["--config", str(DEFAULT_CONFIG_PATH), "--pose2d", str(pose2d), "--out", str(out)]
    )
    err = capsys.readouterr().err
    assert status == 128 + signal.SIGTERM, err
    assert err.rstrip().endswith("stopped by SIGTERM") and "failed on" not in err
    assert not out.exists()
