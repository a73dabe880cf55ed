"""A DeepFly3D lab: the real sample recording (7 cameras, 15 frames) with DeepFly3D 0.x's
own 2D (``df3d_result_2d.pkl``), filmed as videos (``camera_N.mp4``) or, as DeepFly3D
itself reads footage, as image sequences (``camera_N_img_M.jpg``); then a correction
saved in the seed GUI's ``corrections.h5`` layout and a re-run.

Each lab folder holds copies of the sample's files under their own names; the lab's
config names only what differs from the default. One run per footage kind is shared by
the assertions on it.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from .lab import (
    assert_self_consistent,
    copy_files,
    finished,
    lab_run,
    stored_pose2d,
    table_line,
    write_config,
)
from gui_fixtures import write_seed_sidecar

pytestmark = [pytest.mark.slow, pytest.mark.shared]

HEIGHT, WIDTH = 480, 960
FRONT = 3  # camera_3, view f: DeepFly3D detected nothing there in this file
IMPORT = {"format": "deepfly3d", "files": "df3d_result_2d.pkl"}


def _lab(root, sample, footage: str):
    """The lab's folder ``root/fly1`` and config ``root/my.yaml``; the run from ``root``."""
    patterns = ["*.mp4"] if footage == "videos" else ["*_img_*.jpg"]
    copy_files(sample, root / "fly1", [*patterns, "df3d_result_2d.pkl"])
    config = {"recordings": ["fly1"], "pose2d": {"import": IMPORT}}
    if footage == "images":
        config["sources"] = [
            {"name": f"vid_{view}", "filename": f"camera_{i}_img_*.jpg"}
            for i, view in enumerate(("rh", "rm", "rf", "f", "lf", "lm", "lh"))
        ]
    write_config(root / "my.yaml", config)
    return lab_run(root, "my.yaml")


@pytest.fixture(scope="module")
def video_run(tmp_path_factory, df3d_sample_dir):
    root = tmp_path_factory.mktemp("df3d_videos")
    return root, _lab(root, df3d_sample_dir, "videos")


@pytest.fixture(scope="module")
def image_run(tmp_path_factory, df3d_sample_dir):
    root = tmp_path_factory.mktemp("df3d_images")
    return root, _lab(root, df3d_sample_dir, "images")


@pytest.fixture(params=["video_run", "image_run"])
def sample_run(request):
    return request.getfixturevalue(request.param)


@pytest.fixture(scope="module")
def df3d_2d(df3d_pickle):
    """The 2D DeepFly3D wrote, in flylib's layout, from the file's published layout
    (``(row/480, col/960)``, missing ``(0, 0)`` or ``(0, 1)`` in the mirrored cameras
    4-6, joint j = fly38 point (j + 19) mod 38): ``(V, T, P, 2)`` pixels and
    ``(V, T, P)`` clipped heatmap peaks, NaN where DeepFly3D found nothing."""
    from flylib.interop.safe_pickle import load_restricted

    data = load_restricted(df3d_pickle, "DeepFly3D 2D pickle")
    norm = np.asarray(data["points2d"], float)
    peaks = np.asarray(data["heatmap_confidence"], float)[..., 0]
    n_cams, n_frames, n_joints, _ = norm.shape
    points = np.full(norm.shape, np.nan)
    conf = np.full(norm.shape[:3], np.nan)
    for c in range(n_cams):
        missing = (norm[c, ..., 0] == 0) & (norm[c, ..., 1] == (1 if c >= 4 else 0))
        for j in range(n_joints):
            p = (j + 19) % n_joints
            seen = ~missing[:, j]
            points[c, seen, p, 0] = norm[c, seen, j, 1] * WIDTH
            points[c, seen, p, 1] = norm[c, seen, j, 0] * HEIGHT
            conf[c, seen, p] = np.clip(peaks[c, seen, j % peaks.shape[-1]], 0, 1)
    return points, conf


def test_the_sample_runs_to_the_end_with_the_warnings_a_lab_needs(sample_run):
    root, proc = sample_run
    out = finished(proc)
    cells = table_line(out, "fly1")
    assert cells[1] == "15" and cells[-1] == "fly1/flylib_outputs"
    assert "fly1/df3d_result_2d.pkl: no observed point in view 'f' in any frame" in out
    assert "fly1/df3d_result_2d.pkl: 1 score outside [0, 1]" in out
    for name in ("results.h5", "summary.json", "calibration.toml", "pose2d.mp4", "angles.csv"):
        assert (root / "fly1" / "flylib_outputs" / name).stat().st_size > 0


def test_the_stored_2d_is_deepfly3ds_own(sample_run, df3d_2d):
    root, proc = sample_run
    finished(proc)
    points, conf = df3d_2d
    results = root / "fly1" / "flylib_outputs" / "results.h5"
    np.testing.assert_allclose(stored_pose2d(results), points, rtol=0, atol=1e-9)
    from flylib.results import PoseResult

    stored = PoseResult.load(results)
    assert stored.cameras.names == ["rh", "rm", "rf", "f", "lf", "lm", "lh"]
    seen = np.isfinite(points).all(-1)
    np.testing.assert_allclose(stored.conf[seen], conf[seen], rtol=0, atol=1e-9)
    assert np.isnan(stored.pts2d[FRONT]).all() and np.isnan(stored.reproj_error[FRONT]).all()


def test_the_result_agrees_with_itself(sample_run):
    root, proc = sample_run
    finished(proc)
    result = assert_self_consistent(root / "fly1" / "flylib_outputs" / "results.h5")
    assert result.pts3d.shape == (15, 38, 3)
    assert np.isfinite(result.pts3d).all(-1).mean() > 0.95
    assert np.nanmedian(result.reproj_error) < 5.0


def test_videos_and_image_sequences_give_the_same_result(video_run, image_run):
    from flylib.results import PoseResult

    for _, proc in (video_run, image_run):
        finished(proc)
    a, b = (
        PoseResult.load(root / "fly1" / "flylib_outputs" / "results.h5")
        for root, _ in (video_run, image_run)
    )
    np.testing.assert_array_equal(a.pts2d, b.pts2d)
    np.testing.assert_allclose(a.pts3d, b.pts3d, rtol=1e-9, atol=1e-9)
    assert "0.2 fps, not plausible" in video_run[1].out


# -- a correction saved by the seed's GUI, then a re-run ------------------------------------


@pytest.fixture(scope="module")
def corrected_run(video_run, tmp_path_factory):
    """A copy of the finished video lab after a review in the seed's GUI: 16 detections
    moved by a few pixels (every other one also marked fixed) and one marked invisible,
    saved as ``corrections.h5`` beside its results; then the lab runs again."""
    from flylib.results import PoseResult

    source, proc = video_run
    finished(proc)
    root = tmp_path_factory.mktemp("df3d_corrected") / "lab"
    shutil.copytree(source, root, symlinks=True)
    out = root / "fly1" / "flylib_outputs"
    before = PoseResult.load(out / "results.h5")
    detected = stored_pose2d(out / "results.h5")
    rng = np.random.default_rng(36)
    seen = np.argwhere(np.isfinite(detected).all(-1))
    picked = [tuple(int(i) for i in seen[k]) for k in rng.choice(len(seen), 17, replace=False)]
    edits = [(*vtp, *(detected[vtp] + rng.normal(0.0, 6.0, 2))) for vtp in picked[:16]]
    write_seed_sidecar(
        out / "corrections.h5",
        before.pts2d.shape[:3],
        edits2d=edits,
        fixed=picked[:16:2],
        invisible=picked[16:],
    )
    rerun = lab_run(root, "my.yaml")
    return root, before, rerun, {"edits": edits, "invisible": picked[16]}


def test_a_gui_correction_reruns_from_triangulation_and_moves_the_corrected_points(
    corrected_run,
):
    from flylib.corrections import read_corrected
    from flylib.results import PoseResult

    root, before, rerun, changes = corrected_run
    out = finished(rerun)
    assert "rule triangulation:" in out and "rule pose2d:" not in out
    assert "rule bundle_adjustment:" not in out
    results = root / "fly1" / "flylib_outputs" / "results.h5"
    after = PoseResult.load(results)
    touched = {(t, p) for _, t, p, *_ in changes["edits"]} | {changes["invisible"][1:]}
    marks = read_corrected(results)
    assert marks is not None and {tuple(tp) for tp in np.argwhere(marks)} == touched
    t, p = zip(*touched)
    assert not np.allclose(after.pts3d[t, p], before.pts3d[t, p])
    np.testing.assert_array_equal(after.cameras.rvecs, before.cameras.rvecs)


def test_after_a_correction_results_h5_stores_the_2d_its_3d_was_solved_from(corrected_run):
    from flylib.results import PoseResult

    root, _, rerun, changes = corrected_run
    finished(rerun)
    after = PoseResult.load(root / "fly1" / "flylib_outputs" / "results.h5")
    for v, t, p, x, y in changes["edits"]:
        np.testing.assert_allclose(after.pts2d[v, t, p], (x, y), rtol=0, atol=1e-9)
    assert np.isnan(after.pts2d[changes["invisible"]]).all()
    distance = np.linalg.norm(after.pts2d - after.cameras.project(after.pts3d), axis=-1)
    np.testing.assert_allclose(after.reproj_error, distance, atol=1e-6, equal_nan=True)
