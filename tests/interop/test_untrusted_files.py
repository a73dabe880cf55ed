"""Untrusted files (2D import, calibrations, checkpoints): they never run code, and each
mistake in another tool's file is one line naming the file (and camera / key) and the fix."""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path

import h5py
import numpy as np
import pytest

from flylib.config import Config
from flylib.errors import FlylibError, ImportFormatError
from flylib.interop import (
    FLY38_POINT_NAMES,
    ImportTarget,
    import_points2d,
    load_calibration,
    read_anipose_toml,
    read_dlc_csv,
    read_dlc_h5,
    read_sleap_analysis,
    write_dlc_csv,
)
from flylib.interop.safe_pickle import ALLOWED_GLOBALS, load_restricted
from flylib.pipeline.pose2d import import_target

DATA = Path(__file__).resolve().parents[1] / "data" / "interop"


def _target(data: dict):
    """What imported 2D is placed on under the raw config ``data``."""
    return import_target(Config.from_dict(data))


def _config(views, points, **extra) -> dict:
    data = {
        "cameras": {v: {} for v in views},
        "skeleton": {"name": "t", "point_names": list(points)},
    }
    data.update(extra)
    return data


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text, text
    return text


# -- restricted unpickling -------------------------------------------------------------


class _TouchFile:
    """Unpickling this calls ``open(target, "w")``: it creates a file."""

    def __init__(self, target: Path):
        self.target = str(target)

    def __reduce__(self):
        return (open, (self.target, "w"))


class _SystemCall:
    """Unpickling this runs ``os.system("touch target")``."""

    def __init__(self, target: Path):
        self.target = str(target)

    def __reduce__(self):
        return (os.system, (f"touch {self.target}",))


@pytest.mark.parametrize("payload, refused", [(_TouchFile, ".open'"), (_SystemCall, ".system'")])
def test_df3d_2d_pickle_payload_never_runs(tmp_path, payload, refused):
    target = tmp_path / "pwned"
    path = tmp_path / "df3d_result_evil.pkl"
    data = {
        "points2d": np.full((2, 3, 2, 2), 0.5),
        "camera_ordering": np.arange(2),
        "x": payload(target),
    }
    path.write_bytes(pickle.dumps(data))
    with pytest.raises(ImportFormatError) as err:
        import_points2d(
            _target(_config(["a", "b"], ["p0", "p1"])),
            tmp_path,
            {"format": "deepfly3d", "image_size": [10, 10], "keypoint_map": {0: "p0", 1: "p1"}},
        )
    text = _one_line(err)
    assert str(path) in text and refused in text and "refused" in text
    assert not target.exists()


@pytest.mark.parametrize("protocol", [0, 2, 5])
def test_df3d_calibration_pickle_payload_never_runs(tmp_path, protocol):
    target = tmp_path / "pwned"
    calib = {
        0: {"R": np.eye(3), "tvec": np.zeros(3), "intr": np.eye(3), "hook": _TouchFile(target)}
    }
    path = tmp_path / "calib.pkl"
    path.write_bytes(pickle.dumps(calib, protocol=protocol))
    with pytest.raises(
        ImportFormatError, match=r"calib\.pkl: refused .*'(builtins|__builtin__|io)\.open'"
    ) as err:
        load_calibration({"file": str(path)}, ["a"])
    _one_line(err)
    assert not target.exists()


def test_df3d_sample_pickle_loads_bit_identically(df3d_pickle):
    with df3d_pickle.open("rb") as fh:
        trusted = pickle.load(fh)
    ours = load_restricted(df3d_pickle, "DeepFly3D 2D result")
    assert list(ours) == list(trusted)
    for key, value in trusted.items():
        assert type(ours[key]) is type(value)
        assert ours[key].dtype == value.dtype and ours[key].shape == value.shape
        assert ours[key].tobytes() == value.tobytes()


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
@pytest.mark.parametrize("numpy_path", ["numpy.core", "numpy._core"])
def test_numpy_1_and_2_module_paths_and_plain_data_load(tmp_path, protocol, numpy_path):
    """NumPy 1.x pickles name numpy.core.multiarray, 2.x numpy._core.multiarray."""
    data = {
        "a": np.arange(6.0).reshape(2, 3),
        "i": np.int64(3),
        "f": np.float32(0.5),
        "s": "text",
        "l": [1, 2.5, None, True],
        "t": (1, b"x"),
        "set": {1, 2},
        "c": 1j,
        "rec": np.zeros(2, "<f8,<i4"),
    }
    raw = pickle.dumps(data, protocol=protocol)
    if (
        protocol <= 2
    ):  # GLOBAL opcodes are text lines: rewrite the module path as the other NumPy writes it
        for other in ("numpy._core", "numpy.core"):
            raw = raw.replace(f"c{other}.".encode(), f"c{numpy_path}.".encode())
    path = tmp_path / "x.pkl"
    path.write_bytes(raw)
    back = load_restricted(path, "test")
    assert set(back) == set(data)
    for key in ("a", "rec"):
        assert back[key].tobytes() == data[key].tobytes() and back[key].dtype == data[key].dtype
    assert (
        back["i"] == 3
        and back["f"] == np.float32(0.5)
        and back["l"] == data["l"]
        and back["set"] == {1, 2}
    )


def test_allow_list_holds_no_callable_that_reaches_the_system():
    names = {f"{m}.{n}" for m, n in ALLOWED_GLOBALS}
    for bad in (
        "builtins.eval",
        "builtins.exec",
        "builtins.open",
        "builtins.getattr",
        "builtins.__import__",
        "os.system",
        "subprocess.Popen",
        "numpy.load",
    ):
        assert bad not in names


def test_dlc_h5_pickled_metadata_cannot_name_a_global(tmp_path):
    """pandas keeps a DLC .h5's column names as pickles; one naming a global is refused."""
    target = tmp_path / "pwned"
    path = tmp_path / "a.h5"
    path.write_bytes((DATA / "dlc_table.h5").read_bytes())
    with h5py.File(path, "r+") as f:
        f["df_with_missing/table"].attrs["values_block_0_kind"] = np.bytes_(
            pickle.dumps(_TouchFile(target), 0)
        )
    with pytest.raises(
        ImportFormatError, match=r"a\.h5: refused or unreadable pickled pandas metadata"
    ) as err:
        read_dlc_h5(path)
    _one_line(err)
    assert not target.exists()


# -- DeepFly3D 2D content -----------------------------------------------------------------


def _df3d(tmp_path: Path, **payload) -> Path:
    data = {"points2d": np.full((2, 3, 38, 2), 0.5), "camera_ordering": np.arange(2), **payload}
    path = tmp_path / "df3d_result_x.pkl"
    path.write_bytes(pickle.dumps(data))
    return path


def _import_df3d(tmp_path, **spec):
    return import_points2d(
        _target(_config(["a", "b"], FLY38_POINT_NAMES)),
        tmp_path,
        {"format": "deepfly3d", "image_size": [480, 960], **spec},
    )


@pytest.mark.parametrize(
    "payload, message",
    [
        ({"points2d": "0.5 0.5"}, r"'points2d' is a str \('0.5 0.5'\), not numbers"),
        ({"points2d": [[1.0, 2.0], [3.0]]}, r"'points2d' is not a regular array"),
        (
            {"points2d": np.zeros((2, 3, 38))},
            r"'points2d' has shape \(2, 3, 38\), expected \(cameras, frames, joints, 2\)",
        ),
        (
            {"camera_ordering": "0123456"},
            r"'camera_ordering' is a str \('0123456'\), not numbers.*2 distinct integer",
        ),
        (
            {"camera_ordering": np.array([0, 0])},
            r"'camera_ordering' is \[0.0, 0.0\]; it must list 2 distinct integer",
        ),
        (
            {"heatmap_confidence": np.ones((2, 3, 5, 1))},
            r"'heatmap_confidence' shape \(2, 3, 5\) does not fit",
        ),
    ],
)
def test_df3d_bad_content_is_one_line_naming_the_key(tmp_path, payload, message):
    path = _df3d(tmp_path, **payload)
    with pytest.raises(ImportFormatError, match=message) as err:
        _import_df3d(tmp_path)
    assert _one_line(err).startswith(str(path))


def test_df3d_with_30_joints_asks_for_a_keypoint_map(tmp_path):
    path = _df3d(tmp_path, points2d=np.full((2, 3, 30, 2), 0.5))
    with pytest.raises(ImportFormatError) as err:
        _import_df3d(tmp_path, keypoint_map={0: "rf_claw"})
    text = _one_line(err)
    assert text.startswith(str(path)) and "has 30 joints" in text and "38" in text
    assert "pose2d.import.keypoint_map" in text and "joints 1-29" in text
    full = {j: (FLY38_POINT_NAMES[j] if j < 20 else None) for j in range(30)}
    data = _import_df3d(tmp_path, keypoint_map=full)
    assert np.isfinite(data.pts2d[:, :, :20]).all() and np.isnan(data.pts2d[:, :, 20:]).all()


# -- nothing observed -----------------------------------------------------------------------


def test_all_missing_2d_is_an_error_naming_the_file(tmp_path):
    """Decision: with no observed point there is nothing to reconstruct, so the import fails
    (before bundle adjustment or triangulation), whatever the later stages are set to."""
    path = _df3d(tmp_path, points2d=np.zeros((2, 3, 38, 2)))  # DeepFly3D's "(0, 0) = not detected"
    with pytest.raises(ImportFormatError, match="no observed point in any view or frame") as err:
        _import_df3d(tmp_path)
    assert _one_line(err).startswith(str(path))
    _df3d(tmp_path)
    with pytest.raises(ImportFormatError, match="at or above likelihood_threshold 2"):
        _import_df3d(tmp_path, likelihood_threshold=2)


def test_a_view_without_observations_warns(tmp_path, caplog):
    norm = np.full((2, 3, 38, 2), 0.5)
    norm[1] = 0.0
    path = _df3d(tmp_path, points2d=norm)
    with caplog.at_level(logging.WARNING, logger="flylib.interop"):
        data = _import_df3d(tmp_path)
    assert np.isnan(data.pts2d[1]).all()
    assert f"{path}: no observed point in view 'b'" in caplog.text


# -- DeepLabCut CSV -------------------------------------------------------------------------


def test_dlc_csv_first_frame_empty_is_kept(tmp_path):
    xy = np.arange(4 * 2 * 2, dtype=float).reshape(4, 2, 2)
    xy[0] = np.nan
    xy[2, 1] = np.nan
    path = write_dlc_csv(tmp_path / "a.csv", xy, None, ["p", "q"])
    assert path.read_text().splitlines()[3] == "0,,,,,,"
    kp = read_dlc_csv(path)
    assert kp.xy.shape == (4, 2, 2)
    np.testing.assert_array_equal(kp.xy, xy)


def test_flylib_export_dlc_dir_imports_back_with_empty_first_frame(tmp_path):
    from flylib.camera.rig import CameraGroup
    from flylib.cli import main
    from flylib.results import PoseResult
    from flylib.skeleton import Skeleton

    views = ["a", "b", "c"]
    skeleton = Skeleton(point_names=("p0", "p1"), limbs={"leg": ("p0", "p1")}, palette={}, name="t")
    cameras = CameraGroup.from_arrays(
        views,
        np.zeros((3, 3)),
        np.tile([0.0, 0.0, 110.0], (3, 1)),
        np.tile([16000.0, 16000.0, 480.0, 240.0], (3, 1)),
        np.zeros((3, 5)),
    )
    rng = np.random.default_rng(5)
    pts2d = rng.uniform(0, 960, size=(3, 6, 2, 2))
    conf = rng.uniform(0.1, 1, size=(3, 6, 2))
    pts2d[1, 0] = np.nan  # view b sees nothing in frame 0: its CSV's first data row is empty
    pts2d[0, 3, 1] = np.nan
    pts2d[2, -1] = np.nan  # and the last row
    conf[~np.isfinite(pts2d).all(-1)] = np.nan
    result = PoseResult(
        cameras=cameras,
        skeleton=skeleton,
        pts2d=pts2d,
        conf=conf,
        image_sizes={v: (480, 960) for v in views},
    )
    result.save(tmp_path / "results.h5")
    out = tmp_path / "dlc"
    assert main(["export", str(tmp_path / "results.h5"), "--dlc-dir", str(out)]) == 0
    assert (out / "b.csv").read_text().splitlines()[3] == "0,,,,,,"
    back = import_points2d(
        _target(_config(views, ["p0", "p1"])), out, {"format": "dlc_csv", "image_size": [480, 960]}
    )
    np.testing.assert_array_equal(back.pts2d, pts2d)
    np.testing.assert_array_equal(back.conf, conf)


DLC_HEADER = "scorer,{s}\nbodyparts,{b}\ncoords,{c}\n"


def _dlc_text(parts, rows=3) -> str:
    s = ",".join(["DLC"] * 3 * len(parts))
    b = ",".join(p for p in parts for _ in range(3))
    c = ",".join(["x", "y", "likelihood"] * len(parts))
    body = "".join(
        f"{t}," + ",".join(["1.5", "2.5", "0.9"] * len(parts)) + "\n" for t in range(rows)
    )
    return DLC_HEADER.format(s=s, b=b, c=c) + body


def test_dlc_csv_missing_body_parts_warns_naming_file_and_parts(tmp_path, caplog):
    parts = ["p0", "p1", "p2", "p3", "p4"]
    (tmp_path / "a.csv").write_text(_dlc_text(parts))
    (tmp_path / "b.csv").write_text(_dlc_text(["p0", "p4"]))
    with caplog.at_level(logging.WARNING, logger="flylib.interop"):
        data = import_points2d(
            _target(_config(["a", "b"], parts)),
            tmp_path,
            {"format": "dlc_csv", "image_size": [9, 9]},
        )
    assert np.isnan(data.pts2d[1, :, 1:4]).all()
    message = [r.getMessage() for r in caplog.records if "b.csv" in r.getMessage()]
    assert len(message) == 1 and "['p1', 'p2', 'p3']" in message[0] and "view 'b'" in message[0]
    assert "a.csv" not in caplog.text


def test_dlc_csv_lacking_the_other_side_is_fine_when_the_plan_says_the_view_sees_one_side(
    tmp_path, caplog
):
    """A camera sees one side of the fly: its file rightly lacks the other side's parts.
    With a detection plan (pose2d.output_points) only parts the plan gives that view count."""
    parts = ["p0", "p1", "p2", "p3"]
    (tmp_path / "a.csv").write_text(_dlc_text(["p0", "p1"]))
    (tmp_path / "b.csv").write_text(_dlc_text(["p2"]))
    plan_points = {"a": ("p0", "p1"), "b": ("p2", "p3")}  # pose2d.output_points' views
    target = ImportTarget(views=("a", "b"), point_names=tuple(parts), plan_points=plan_points)
    with caplog.at_level(logging.WARNING, logger="flylib.interop"):
        import_points2d(
            target,
            tmp_path,
            {"format": "dlc_csv", "image_size": [9, 9]},
        )
    assert "a.csv" not in caplog.text  # p2, p3 are the other side's
    message = [r.getMessage() for r in caplog.records if "b.csv" in r.getMessage()]
    assert len(message) == 1 and "['p3']" in message[0] and "output_points" in message[0]


@pytest.mark.parametrize(
    "text, message",
    [
        ("scorer,DLC,DLC\nbodyparts,p,p\ncoords,x,y\n0,1,2,3,4\n", "malformed CSV row"),
        ("scorer,DLC,DLC\nbodyparts,p,p\n0,1,2\n", "not a DeepLabCut CSV"),
        (b"scorer,\xff\xfe\n".decode("latin-1"), "not a readable CSV .*utf-8"),
        ("scorer,DLC,DLC\nbodyparts,p,p\ncoords,x,y\n0,a,b\n", "non-numeric cell"),
    ],
)
def test_dlc_csv_damage_is_one_line(tmp_path, text, message):
    path = tmp_path / "a.csv"
    path.write_text(text, encoding="latin-1")
    with pytest.raises(ImportFormatError, match=message) as err:
        read_dlc_csv(path)
    assert _one_line(err).startswith(str(path))


def test_dlc_csv_header_only_is_zero_frames(tmp_path):
    path = tmp_path / "a.csv"
    path.write_text("scorer,DLC,DLC\nbodyparts,p,p\ncoords,x,y\n")
    assert read_dlc_csv(path).xy.shape == (0, 1, 2)


# -- SLEAP files written by sleap-io ----------------------------------------------------------


def _sleap_labels(n_frames: int, detect: bool):
    sio = pytest.importorskip("sleap_io")
    skeleton = sio.Skeleton(["head", "thorax", "abdomen"])
    video = sio.Video(filename="camera_0.mp4")
    track = sio.Track("fly")
    frames = []
    for t in range(n_frames):
        instances = []
        if detect:
            points = np.array([[10.0 + t, 20.0], [30.0, 40.0 + t], [np.nan, np.nan]])
            instances.append(
                sio.PredictedInstance.from_numpy(
                    points,
                    skeleton=skeleton,
                    point_scores=np.array([0.9, 0.8, 0.0]),
                    score=1.0,
                    track=track,
                )
            )
        frames.append(sio.LabeledFrame(video=video, frame_idx=t, instances=instances))
    return sio, sio.Labels(
        labeled_frames=frames,
        videos=[video],
        skeletons=[skeleton],
        tracks=[track] if detect else [],
    )


def test_sleap_io_analysis_file_with_one_track(tmp_path):
    sio, labels = _sleap_labels(5, detect=True)
    path = tmp_path / "a.analysis.h5"
    sio.save_analysis_h5(labels, str(path))
    kp = read_sleap_analysis(path)
    assert kp.names == ["head", "thorax", "abdomen"] and kp.xy.shape == (5, 3, 2)
    np.testing.assert_allclose(kp.xy[:, 0, 0], 10.0 + np.arange(5))
    np.testing.assert_allclose(kp.conf[:, :2], np.tile([0.9, 0.8], (5, 1)))
    assert np.isnan(kp.xy[:, 2]).all() and np.isnan(kp.conf[:, 2]).all()


def test_sleap_io_analysis_file_with_zero_tracks_imports_as_missing(tmp_path, caplog):
    """What SLEAP writes for a camera in which nothing was detected: tracks (0, 2, K, T)."""
    sio, empty = _sleap_labels(5, detect=False)
    sio.save_analysis_h5(empty, str(tmp_path / "b.analysis.h5"))
    with h5py.File(tmp_path / "b.analysis.h5") as f:
        assert f["tracks"].shape == (0, 2, 3, 5)
    _, full = _sleap_labels(5, detect=True)
    sio.save_analysis_h5(full, str(tmp_path / "a.analysis.h5"))
    spec = {"format": "sleap", "image_size": [480, 960]}
    with caplog.at_level(logging.WARNING, logger="flylib.interop"):
        data = import_points2d(
            _target(_config(["a", "b"], ["head", "thorax", "abdomen"])), tmp_path, spec
        )
    assert data.pts2d.shape == (2, 5, 3, 2)
    assert np.isnan(data.pts2d[1]).all() and np.isfinite(data.pts2d[0, :, :2]).all()
    assert "b.analysis.h5: holds no tracks" in caplog.text


# -- calibrations: every value checked where it is read -----------------------------------------

ANIPOSE = """
[cam_0]
name = "rh"
size = [960, 480]
matrix = [[16000.0, 0.0, 480.0], [0.0, 16000.0, 240.0], [0.0, 0.0, 1.0]]
distortions = [0.0, 0.0, 0.0, 0.0, 0.0]
rotation = [0.0, 1.0, 0.0]
translation = [0.0, 0.0, 110.0]

[cam_1]
name = "rm"
size = [960, 480]
matrix = [[16000.0, 0.0, 480.0], [0.0, 16000.0, 240.0], [0.0, 0.0, 1.0]]
distortions = [0.0, 0.0, 0.0, 0.0, 0.0]
rotation = [0.0, 0.5, 0.0]
translation = [0.0, 0.0, 110.0]

[cam_2]
name = "rf"
size = [960, 480]
matrix = [[16000.0, 0.0, 480.0], [0.0, 16000.0, 240.0], [0.0, 0.0, 1.0]]
distortions = [0.0, 0.0, 0.0, 0.0, 0.0]
rotation = [0.0, 0.2, 0.0]
translation = [0.0, 0.0, 110.0]
"""


def _cam2(line_old: str, line_new: str) -> str:
    head, cam2 = ANIPOSE.split("[cam_2]")
    assert line_old in cam2
    return head + "[cam_2]" + cam2.replace(line_old, line_new)


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("[0.0, 16000.0, 240.0]", "[0.0, nan, 240.0]", r"'matrix' holds NaN or infinite values"),
        (
            "translation = [0.0, 0.0, 110.0]",
            "translation = [0.0, nan, 110.0]",
            r"'translation' holds NaN",
        ),
        ("rotation = [0.0, 0.2, 0.0]", "rotation = [0.0, inf, 0.0]", r"'rotation' holds NaN"),
        (
            "size = [960, 480]",
            'size = ["wide", 480]',
            r"'size' is \['wide', 480\]; it must be \[width, height\]",
        ),
        ("size = [960, 480]", "size = [960]", r"'size' is \[960\]"),
        (
            "distortions = [0.0, 0.0, 0.0, 0.0, 0.0]",
            f"distortions = {[0.0] * 20}",
            r"'distortions' has 20 values; it must be at most 12",
        ),
        (
            "distortions = [0.0, 0.0, 0.0, 0.0, 0.0]",
            'distortions = ["k1"]',
            r"'distortions' is a list \(\['k1'\]\), not numbers",
        ),
        (
            "translation = [0.0, 0.0, 110.0]",
            "translation = [0.0, 110.0]",
            r"'translation' has shape \(2,\); it must be 3 numbers",
        ),
        ("[0.0, 0.0, 1.0]]", "[0.0, 1.0, 1.0]]", r"'matrix' is .* it must be a 3x3 camera matrix"),
        ('name = "rf"', "name = [1]", r"\[cam_2\]: 'name' is \[1\]"),
    ],
)
def test_anipose_bad_value_names_file_section_camera_and_key(tmp_path, old, new, message):
    path = tmp_path / "calibration.toml"
    path.write_text(_cam2(old, new))
    with pytest.raises(ImportFormatError, match=message) as err:
        load_calibration({"file": str(path)}, ["rh", "rm", "rf"])
    text = _one_line(err)
    assert text.startswith(f"{path} [cam_2]")
    if "'name'" not in text:
        assert "(name 'rf')" in text


def test_anipose_good_file_still_loads(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(ANIPOSE)
    cams = read_anipose_toml(path)
    assert list(cams) == ["rh", "rm", "rf"] and cams["rf"]["size"] == (960, 480)


@pytest.mark.parametrize(
    "key, value, message",
    [
        (
            "intr",
            np.array([[np.nan, 0, 480], [0, 16000.0, 240], [0, 0, 1]]),
            r"camera 1: 'intr' holds NaN",
        ),
        ("tvec", np.array([0.0, np.nan, 110.0]), r"camera 1: 'tvec' holds NaN"),
        ("tvec", "0 0 110", r"camera 1: 'tvec' is a str"),
        ("R", np.eye(3) * 2, r"camera 1: 'R' is not a rotation"),
        ("distort", np.zeros(20), r"camera 1: 'distort' has 20 values"),
    ],
)
def test_df3d_calibration_bad_value_names_camera_and_key(tmp_path, key, value, message):
    good = {
        "R": np.eye(3),
        "tvec": np.array([0.0, 0.0, 110.0]),
        "intr": np.array([[16000.0, 0, 480], [0, 16000.0, 240], [0, 0, 1]]),
        "distort": np.zeros(5),
    }
    calib = {0: dict(good), 1: {**good, key: value}}
    path = tmp_path / "calib.pkl"
    path.write_bytes(pickle.dumps(calib))
    with pytest.raises(ImportFormatError, match=message) as err:
        load_calibration({"file": str(path)}, ["a", "b"])
    assert _one_line(err).startswith(str(path))


def test_errors_are_flylib_errors():
    assert issubclass(ImportFormatError, FlylibError)


# -- detector checkpoints ---------------------------------------------------------------------


def test_checkpoint_with_a_payload_is_refused_and_never_runs(tmp_path):
    torch = pytest.importorskip("torch")
    from flylib.errors import WeightsError
    from flylib.pose2d.weights import read_state_dict

    target = tmp_path / "pwned"
    path = tmp_path / "evil.tar"
    torch.save({"state_dict": {"conv1.weight": torch.zeros(1)}, "hook": _TouchFile(target)}, path)
    with pytest.raises(
        WeightsError, match=r"evil\.tar: cannot read the checkpoint \(it holds an object of class "
    ) as err:
        read_state_dict(path)
    line = _one_line(err)
    assert "weights_only" not in line  # torch's advice to load it anyway, running its code
    assert not target.exists()
    good = tmp_path / "good.tar"
    torch.save({"state_dict": {"module.conv1.weight": torch.ones(2)}}, good)
    assert list(read_state_dict(good)) == ["conv1.weight"]
    (tmp_path / "cut.tar").write_bytes(good.read_bytes()[:100])
    with pytest.raises(WeightsError, match=r"cut\.tar: cannot read the checkpoint"):
        read_state_dict(tmp_path / "cut.tar")
