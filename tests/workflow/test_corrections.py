"""The workflow applies a recording's corrections.h5: saving one re-runs exactly
triangulation, assemble and visualization of that recording, and the re-run marks the
corrected points in results.h5 and rings them in the videos."""

from __future__ import annotations

import copy
import json

import h5py
import numpy as np
import pytest

from flylib.corrections import Corrections, read_corrected
from flylib.results import Pose2dData, PoseResult
from tests.workflow.test_workflow import base_config, jobs, make_recording, planned, snakemake

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("corrections_workflow")
    config = base_config()
    config["bundle_adjustment"]["max_nfev"] = 20
    config["recordings"] = [
        make_recording(config, root / name, seed) for seed, name in enumerate(("recA", "recB"))
    ]
    snakemake(root, config=config)
    return root, config


def an_edit(out):
    """A corrections sidecar moving one well-seen point of recA by a few pixels."""
    pose2d = Pose2dData.load(out / "stages" / "pose2d.h5")
    seen = np.isfinite(pose2d.pts2d).all(-1)
    t = 2
    p = int(np.flatnonzero(seen[:, t].sum(axis=0) >= 3)[0])
    v = int(np.flatnonzero(seen[:, t, p])[0])
    corr = Corrections.empty(*seen.shape, source=str(out / "results.h5"))
    corr.set_point(v, t, p, pose2d.pts2d[v, t, p] + [5.0, 5.0])
    q = int(np.flatnonzero(seen[:, 4].sum(axis=0) >= 3)[1])
    corr.set_invisible(int(np.flatnonzero(seen[:, 4, q])[0]), 4, q)
    return corr, (t, p), (4, q)


def test_saved_corrections_rerun_exactly_triangulation_assemble_visualization(runs):
    root, config = runs
    out = root / "recA" / "flylib_outputs"
    assert planned(root, config) == set()
    before = PoseResult.load(out / "results.h5")
    with h5py.File(out / "results.h5") as f:
        tri_before = f["triangulation/points3d"][()]
    video_before = (out / "pose2d.mp4").read_bytes()
    corr, (t, p), (t2, q) = an_edit(out)
    corr.save(out / "corrections.h5")
    assert planned(root, config) == jobs(
        ("triangulation", "refinement", "assemble", "visualization", "kinematics"), ("recA",)
    )

    snakemake(root, config=config)
    assert planned(root, config) == set()
    after = PoseResult.load(out / "results.h5")
    marks = read_corrected(out / "results.h5")
    assert marks is not None and marks[t, p] and marks[t2, q] and marks.sum() == 2
    assert not np.allclose(after.pts3d[t, p], before.pts3d[t, p])
    untouched = ~marks
    with h5py.File(out / "results.h5") as f:
        tri_after = f["triangulation/points3d"][()]
    # triangulation solves each point alone: only the corrected ones move there; the
    # refinement after it couples frames, but keeps the corrected points as triangulated
    np.testing.assert_allclose(tri_after[untouched], tri_before[untouched], equal_nan=True)
    np.testing.assert_array_equal(after.pts3d[marks], tri_after[marks])
    with h5py.File(out / "results.h5") as f:
        assert json.loads(f["triangulation"].attrs["corrections"])["count"] == 2
    assert read_corrected(root / "recB" / "flylib_outputs" / "results.h5") is None
    assert (out / "pose2d.mp4").read_bytes() != video_before  # re-rendered with the rings

    # saving again (a newer file) re-runs the same three jobs; deleting it does too
    corr.set_point(0, 0, 0, (100.0, 100.0))
    corr.save(out / "corrections.h5")
    assert planned(root, config) == jobs(
        ("triangulation", "refinement", "assemble", "visualization", "kinematics"), ("recA",)
    )
    (out / "corrections.h5").unlink()
    assert planned(root, config) == jobs(
        ("triangulation", "refinement", "assemble", "visualization", "kinematics"), ("recA",)
    )


def test_the_config_can_name_the_sidecar(runs, tmp_path):
    root, config = runs
    config = copy.deepcopy(config)
    config["corrections"] = str(tmp_path / "{name}_fixes.h5")
    out = root / "recB" / "flylib_outputs"
    corr, *_ = an_edit(out)
    corr.save(tmp_path / "recB_fixes.h5")
    proc = snakemake(root, "--dry-run", config=config)
    assert "no such file for recA" in proc.stdout + proc.stderr
    plan = planned(root, config)
    assert ("triangulation", "recB") in plan and ("pose2d", "recB") not in plan
    assert ("bundle_adjustment", "recB") not in plan


def test_after_a_correction_results_h5_agrees_with_itself_and_the_dlc_export_is_the_detections(
    runs, tmp_path
):
    """Issue 36 (5, 7): the re-run stores the corrected 2D (not the detection) where the
    3D was solved from it, errors that match the stored 2D, 3D and cameras, and
    `flylib export --dlc-dir` writes pose2d's 2D with the correction applied."""
    import subprocess
    import sys

    from flylib.interop.dlc import read_dlc_csv
    from flylib.results import check_results, read_detections

    root, config = runs
    out = root / "recA" / "flylib_outputs"
    pose2d = Pose2dData.load(out / "stages" / "pose2d.h5")
    seen = np.isfinite(pose2d.pts2d).all(-1)
    t = 3
    p = int(np.flatnonzero(seen[:, t].sum(axis=0) >= 3)[2])
    v = int(np.flatnonzero(seen[:, t, p])[0])
    edit = pose2d.pts2d[v, t, p] + [12.0, -9.0]
    corr = Corrections.empty(*seen.shape, source=str(out / "results.h5"))
    corr.set_point(v, t, p, edit, fixed=True)  # kept whatever the robust fit thinks of it
    corr.save(out / "corrections.h5")
    snakemake(root, config=config)

    assert check_results(out / "results.h5") == []
    verify = subprocess.run(
        [sys.executable, "-m", "flylib.cli", "inspect", "--verify", str(out / "results.h5")],
        capture_output=True,
        text=True,
    )
    assert verify.returncode == 0 and "consistent" in verify.stdout, verify.stderr
    result = PoseResult.load(out / "results.h5")
    np.testing.assert_array_equal(result.pts2d[v, t, p], edit)
    projected = result.cameras.project(result.pts3d)
    distance = np.linalg.norm(result.pts2d - projected, axis=-1)
    np.testing.assert_allclose(result.reproj_error, distance, atol=1e-6, equal_nan=True)
    with h5py.File(out / "results.h5") as f:  # the detection itself stays in pose2d/
        np.testing.assert_array_equal(f["pose2d/points"][v, t, p], pose2d.pts2d[v, t, p])

    dlc = tmp_path / "dlc"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "flylib.cli",
            "export",
            str(out / "results.h5"),
            "--dlc-dir",
            str(dlc),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    assert "pose2d's detections, 1 observations corrected by hand" in proc.stderr
    expected = pose2d.pts2d.copy()
    expected[v, t, p] = edit
    detections = read_detections(out / "results.h5")
    np.testing.assert_array_equal(detections.points, expected)
    for i, view in enumerate(result.cameras.names):
        back = read_dlc_csv(dlc / f"{view}.csv")
        assert list(back.names) == list(result.skeleton.point_names)
        np.testing.assert_array_equal(back.xy, expected[i])
        present = np.isfinite(back.xy).all(-1)
        assert not np.isfinite(back.conf[~present]).any()  # no likelihood without x/y
    # every detection is exported, not only those a 3D stage kept
    assert np.isfinite(expected).all(-1).sum() > np.isfinite(result.pts2d).all(-1).sum()
