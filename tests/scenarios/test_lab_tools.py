"""Labs whose 2D or rig comes from another tool, each run end to end as the lab sets it up:

- DeepLabCut: one CSV per camera as DeepLabCut names them (``camera_0DLC_<scorer>.csv``),
  found by a pattern in the top-level ``pose2d.import`` or in the recording's entry;
- SLEAP: one analysis HDF5 per camera, written by ``sleap-io`` (SLEAP's own writer);
- Anipose: the lab's calibration TOML (``[cam_N]`` tables, as aniposelib writes them)
  for a rig other than the default one, with bundle adjustment off.

The 2D comes from a synthetic fly filmed through a known rig (the demo's generator), so
each run can be held against the 2D the lab's files hold and against the 3D truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from .lab import (
    assert_self_consistent,
    copy_files,
    finished,
    lab_run,
    read_dlc_csv,
    similarity_error,
    stored_pose2d,
    synthetic_recording,
    table_line,
    write_config,
)

pytestmark = pytest.mark.slow

FRAMES = 6
VIEWS = ["rh", "rm", "rf", "f", "lf", "lm", "lh"]


def _points():
    from flylib.config import Config

    return list(Config.default().data["skeleton"]["point_names"])


@pytest.fixture(scope="module")
def filmed(tmp_path_factory) -> tuple[Path, dict]:
    """A synthetic recording through the default rig: footage, DeepLabCut CSVs, truth."""
    directory = tmp_path_factory.mktemp("filmed") / "fly1"
    return directory, synthetic_recording(directory, FRAMES, seed=3)


@pytest.fixture(scope="module")
def dlc_2d(filmed) -> np.ndarray:
    """``(V, T, P, 2)``: what the lab's DeepLabCut CSVs hold, read with pandas."""
    directory, _ = filmed
    points = _points()
    return np.stack(
        [read_dlc_csv(directory / f"camera_{i}DLC_flylibdemo.csv", points) for i in range(7)]
    )


#: What the tool scenarios leave out of the lab's run: the videos (nothing here is about them).
NO_VIDEOS = {"do_visualization": False}


@pytest.fixture(scope="module")
def dlc_lab(filmed, tmp_path_factory):
    """One run of two copies of the DeepLabCut recording: ``fly1`` finds its CSVs by the
    pattern in its recordings entry (DeepLabCut's own naming, ``{stem}DLC_*.csv``),
    ``fly2`` by the top-level ``pose2d.import`` (``camera_{index}DLC_<scorer>.csv``)."""
    source, _ = filmed
    root = tmp_path_factory.mktemp("dlc")
    for name in ("fly1", "fly2"):
        copy_files(source, root / name, ["camera_*.mp4", "camera_*DLC_*.csv"])
    entry = {"format": "dlc_csv", "files": "{stem}DLC_*.csv"}
    top = {"format": "dlc_csv", "files": "camera_{index}DLC_flylibdemo.csv"}
    config = {
        "recordings": [{"path": "fly1", "import": entry}, "fly2"],
        "pose2d": {"import": top},
        "pipeline": NO_VIDEOS,
    }
    write_config(root / "my.yaml", config)
    return root, lab_run(root, "my.yaml")


@pytest.mark.parametrize(
    "name", ["fly1", "fly2"], ids=["pattern_in_the_recordings_entry", "top_level_pattern"]
)
def test_deeplabcut_csvs_found_by_a_pattern(dlc_lab, filmed, dlc_2d, name):
    root, proc = dlc_lab
    out = finished(proc)
    assert table_line(out, name)[1] == str(FRAMES)
    results = root / name / "flylib_outputs" / "results.h5"
    np.testing.assert_allclose(stored_pose2d(results), dlc_2d, rtol=0, atol=1e-9)
    result = assert_self_consistent(results)
    assert similarity_error(result.pts3d, filmed[1]["points3d"]) < 0.05


def test_both_patterns_read_the_same_files_to_the_same_result(dlc_lab):
    from flylib.results import PoseResult

    root, proc = dlc_lab
    finished(proc)
    one, two = (
        PoseResult.load(root / n / "flylib_outputs" / "results.h5") for n in ("fly1", "fly2")
    )
    np.testing.assert_array_equal(one.pts2d, two.pts2d)
    np.testing.assert_allclose(one.pts3d, two.pts3d, rtol=1e-9, atol=1e-9)


# -- SLEAP -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sleap_lab(filmed, dlc_2d, tmp_path_factory):
    """The lab's SLEAP analysis files (``camera_N.analysis.h5``, written by sleap-io):
    one fly track per camera, every fly38 point a node, SLEAP's scores (which exceed 1
    at times) on the detected ones."""
    sio = pytest.importorskip("sleap_io")
    source, _ = filmed
    root = tmp_path_factory.mktemp("sleap")
    recording = copy_files(source, root / "fly1", ["camera_*.mp4"])
    points = _points()
    rng = np.random.default_rng(5)
    scores = np.where(np.isfinite(dlc_2d).all(-1), rng.uniform(0.4, 1.25, dlc_2d.shape[:3]), 0.0)
    skeleton = sio.Skeleton(points)
    for i in range(len(VIEWS)):
        video = sio.Video(filename=f"camera_{i}.mp4")
        track = sio.Track("fly")
        frames = [
            sio.LabeledFrame(
                video=video,
                frame_idx=t,
                instances=[
                    sio.PredictedInstance.from_numpy(
                        dlc_2d[i, t],
                        skeleton=skeleton,
                        point_scores=scores[i, t],
                        score=1.0,
                        track=track,
                    )
                ],
            )
            for t in range(FRAMES)
        ]
        labels = sio.Labels(
            labeled_frames=frames, videos=[video], skeletons=[skeleton], tracks=[track]
        )
        sio.save_analysis_h5(labels, str(recording / f"camera_{i}.analysis.h5"))
    spec = {"format": "sleap", "files": "{stem}.analysis.h5"}
    config = {"recordings": [{"path": "fly1", "import": spec}], "pipeline": NO_VIDEOS}
    write_config(root / "my.yaml", config)
    return root, lab_run(root, "my.yaml"), scores


def test_sleap_analysis_files_written_by_sleap_io(sleap_lab, filmed, dlc_2d):
    from flylib.results import PoseResult

    root, proc, scores = sleap_lab
    out = finished(proc)
    assert "fly1/camera_0.analysis.h5" in out and "clipped into [0, 1]" in out
    results = root / "fly1" / "flylib_outputs" / "results.h5"
    np.testing.assert_allclose(stored_pose2d(results), dlc_2d, rtol=0, atol=1e-9)
    seen = np.isfinite(dlc_2d).all(-1)
    conf = PoseResult.load(results).conf
    np.testing.assert_allclose(conf[seen], np.clip(scores[seen], 0, 1), rtol=0, atol=1e-6)
    result = assert_self_consistent(results)
    assert similarity_error(result.pts3d, filmed[1]["points3d"]) < 0.05


# -- an Anipose calibration ----------------------------------------------------------------


def _lab_rig_cameras() -> dict:
    """A ``cameras`` table of the lab's own rig: higher, turned and rolled, unlike the default."""
    import yaml

    from workflow_run import REPO

    cameras = yaml.safe_load((REPO / "config" / "config.yaml").read_text())["cameras"]
    cameras["defaults"].update(elevation_deg=3.0)
    for view in VIEWS:
        cameras[view]["azimuth_deg"] += 6.0
        cameras[view]["roll_deg"] = 1.5
    return cameras


def _anipose_toml(path: Path, rig, size=(960, 480)) -> None:
    """The rig as aniposelib's ``CameraGroup.dump`` writes it (``toml.dump`` layout),
    cameras named after their videos."""
    blocks = []
    for i, cam in enumerate(rig):
        k = cam.kmat
        dist = np.zeros(max(5, cam.dist.size))
        dist[: cam.dist.size] = cam.dist

        def row(values) -> str:
            return "[ " + " ".join(f"{float(x)!r}," for x in values) + "]"

        blocks.append(
            f"[cam_{i}]\n"
            f'name = "camera_{i}"\n'
            f"size = [ {size[0]}, {size[1]},]\n"
            f"matrix = [ {row(k[0])}, {row(k[1])}, {row(k[2])},]\n"
            f"distortions = {row(dist)}\n"
            f"rotation = {row(cam.rvec)}\n"
            f"translation = {row(cam.tvec)}\n\n"
        )
    blocks.append("[metadata]\nadjusted = true\nerror = 0.3\n")
    path.write_text("".join(blocks))


@pytest.fixture(scope="module")
def anipose_lab(tmp_path_factory):
    from flylib.camera.rig import CameraGroup
    from flylib.config import Config

    root = tmp_path_factory.mktemp("anipose")
    cameras = _lab_rig_cameras()
    truth = synthetic_recording(root / "fly1", FRAMES, seed=4, cameras=cameras)
    (root / "fly1" / "truth.h5").rename(root / "truth.h5")  # not the lab's file
    data = Config.default().data
    data["cameras"] = cameras
    rig = CameraGroup.from_config(Config.from_dict(data), {v: (480, 960) for v in VIEWS})
    _anipose_toml(root / "fly1" / "calibration.toml", rig)
    write_config(
        root / "my.yaml",
        {
            "recordings": [
                {"path": "fly1", "import": {"format": "dlc_csv", "files": "{stem}DLC_*.csv"}}
            ],
            "calibration": {
                "file": "calibration.toml",
                "names": {view: f"camera_{i}" for i, view in enumerate(VIEWS)},
            },
            "pipeline": {"do_bundle_adjustment": False, **NO_VIDEOS},
        },
    )
    return root, lab_run(root, "my.yaml"), rig, truth


def test_an_anipose_calibration_is_the_rig_of_the_run(anipose_lab):
    import tomllib

    root, proc, rig, truth = anipose_lab
    finished(proc)
    out = root / "fly1" / "flylib_outputs"
    result = assert_self_consistent(out / "results.h5", bound_px=25.0)
    assert result.cameras.names == VIEWS
    for name in ("rvecs", "tvecs", "intrs"):
        np.testing.assert_allclose(getattr(result.cameras, name), getattr(rig, name), atol=1e-12)
    # the lab's rig is the world: the 3D is the truth itself, no alignment needed
    err = np.linalg.norm(result.pts3d - truth["points3d"], axis=-1)
    extent = np.median(np.linalg.norm(truth["points3d"] - truth["points3d"].mean((0, 1)), axis=-1))
    assert np.nanmedian(err) < 0.02 * extent, (np.nanmedian(err), extent)
    written = tomllib.loads((out / "calibration.toml").read_text())
    for i, cam in enumerate(rig):
        section = next(s for s in written.values() if s.get("name") in (VIEWS[i], f"camera_{i}"))
        np.testing.assert_allclose(section["rotation"], cam.rvec, atol=1e-12)
        np.testing.assert_allclose(section["translation"], cam.tvec, atol=1e-12)
        np.testing.assert_allclose(section["matrix"], cam.kmat, atol=1e-9)
