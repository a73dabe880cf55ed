"""flylib.interop: 2D import (DeepFly3D, DeepLabCut / Lightning Pose, SLEAP), calibrations, exports."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd
import pytest

from flylib.config import Config
from flylib.errors import ImportFormatError
from flylib.interop import (
    FLY38_POINT_NAMES,
    calibration_from_index,
    calibration_inputs,
    df3d_joint_to_fly38,
    import_points2d,
    load_calibration,
    points3d_table,
    read_anipose_toml,
    read_dlc_csv,
    write_anipose_toml,
    write_dlc_views,
    write_points3d_csv,
)
from flylib.pipeline.pose2d import import_target

RIG_VIEWS = ["rh", "rm", "rf", "f", "lf", "lm", "lh"]


def _target(data: dict):
    """What imported 2D is placed on under the raw config ``data``."""
    return import_target(Config.from_dict(data))


def rig_config(views=RIG_VIEWS, points=FLY38_POINT_NAMES, **extra) -> dict:
    """A raw config mapping: views fed by sources camera_<i>.mp4, skeleton points."""
    data = {
        "sources": [
            {"name": f"vid_{v}", "filename": f"camera_{i}.mp4"} for i, v in enumerate(views)
        ],
        "cameras": {"defaults": {}, **{v: {} for v in views}},
        "skeleton": {"name": "test", "point_names": list(points)},
    }
    data.update(extra)
    return data


# -- DeepFly3D 2D pickle -------------------------------------------------------------


def test_df3d_joint_order_is_fly38_shifted_by_19():
    assert df3d_joint_to_fly38(0) == "rf_thorax_coxa"
    assert df3d_joint_to_fly38(14) == "rh_claw"
    assert df3d_joint_to_fly38(15) == "r_antenna"
    assert df3d_joint_to_fly38(18) == "r_abdomen2"
    assert df3d_joint_to_fly38(19) == "lf_thorax_coxa"
    assert df3d_joint_to_fly38(37) == "l_abdomen2"


def test_import_df3d_sample_pickle(df3d_sample_dir, df3d_pickle):
    data = import_points2d(_target(rig_config()), df3d_sample_dir, {"format": "deepfly3d"})
    assert data.view_names == RIG_VIEWS
    assert data.pts2d.shape == (7, 15, 38, 2) and data.conf.shape == (7, 15, 38)
    observed = np.isfinite(data.pts2d).all(-1).sum(axis=(1, 2))
    assert observed.tolist() == [285, 285, 225, 0, 225, 285, 285]
    assert data.image_sizes == {v: (480, 960) for v in RIG_VIEWS}
    idx = {n: i for i, n in enumerate(FLY38_POINT_NAMES)}
    # pixels checked by eye over frame 7 of the decoded videos (see flylib.interop.df3d)
    pinned = {
        ("rm", "r_antenna"): (660.0, 150.0),
        ("rm", "r_abdomen0"): (300.0, 142.5),
        ("rm", "rf_claw"): (780.0, 405.0),
        ("rm", "rh_claw"): (420.0, 382.5),
        ("lm", "l_antenna"): (300.0, 150.0),
        ("lm", "lf_claw"): (142.5, 412.5),
        ("rh", "r_abdomen2"): (202.5, 285.0),
    }
    for (view, point), xy in pinned.items():
        np.testing.assert_array_equal(data.pts2d[RIG_VIEWS.index(view), 7, idx[point]], xy)
    # right flank seen from the right: head (antenna) to the right of the abdomen in rm,
    # to the left in lm (the mirror view)
    rm, lm = RIG_VIEWS.index("rm"), RIG_VIEWS.index("lm")
    assert np.all(data.pts2d[rm, :, idx["r_antenna"], 0] > data.pts2d[rm, :, idx["r_abdomen2"], 0])
    assert np.all(data.pts2d[lm, :, idx["l_antenna"], 0] < data.pts2d[lm, :, idx["l_abdomen2"], 0])
    # left points are never seen from the right cameras and vice versa
    assert np.isnan(data.pts2d[rm, :, idx["lf_claw"]]).all()
    assert np.isnan(data.pts2d[lm, :, idx["rf_claw"]]).all()
    # confidence is the heatmap peak of the joint's channel (joint j -> channel j mod 19)
    with df3d_pickle.open("rb") as fh:
        heat = pickle.load(fh)["heatmap_confidence"][..., 0]
    assert data.conf[rm, 7, idx["r_antenna"]] == heat[1, 7, 15]
    assert data.conf[lm, 7, idx["l_antenna"]] == heat[5, 7, 15]
    assert np.isnan(data.conf[RIG_VIEWS.index("f")]).all()


def _write_df3d_pickle(path: Path, points2d, conf=None) -> Path:
    payload = {"points2d": np.asarray(points2d, float), "camera_ordering": np.arange(len(points2d))}
    if conf is not None:
        payload["heatmap_confidence"] = np.asarray(conf, float)[..., None]
    with path.open("wb") as fh:
        pickle.dump(payload, fh)
    return path


def test_df3d_synthetic_pickle_normalization_and_missing(tmp_path):
    views, points = ["a", "b"], ["p0", "p1"]
    norm = np.zeros((2, 3, 2, 2))
    norm[0, :, 0] = [0.25, 0.5]  # row/h, col/w
    norm[1, :, 1] = [0.5, 0.125]
    norm[1, :, 0] = [0.0, 1.0]  # mirrored camera's "missing"
    norm[0, 2, 1] = [0.0, 0.0]  # missing
    conf = np.full((2, 3, 1), 0.5)
    _write_df3d_pickle(tmp_path / "df3d_result_x.pkl", norm, conf)
    spec = {"format": "deepfly3d", "image_size": [100, 200], "keypoint_map": {0: "p0", 1: "p1"}}
    data = import_points2d(_target(rig_config(views, points)), tmp_path, spec)
    np.testing.assert_array_equal(data.pts2d[0, :, 0], [[100.0, 25.0]] * 3)  # x = col*w, y = row*h
    np.testing.assert_array_equal(data.pts2d[1, :, 1], [[25.0, 50.0]] * 3)
    assert np.isnan(data.pts2d[1, :, 0]).all() and np.isnan(data.pts2d[0, :, 1]).all()
    assert data.image_sizes == {"a": (100, 200), "b": (100, 200)}
    np.testing.assert_array_equal(data.conf[0, :, 0], 0.5)
    assert np.isnan(data.conf[1, :, 0]).all()


def test_df3d_import_errors_name_file_and_fix(tmp_path):
    views, points = ["a", "b"], ["p0", "p1"]
    _write_df3d_pickle(tmp_path / "df3d_result_1.pkl", np.full((2, 3, 2, 2), 0.5))
    config = rig_config(views, points)
    with pytest.raises(ImportFormatError, match="image_size"):  # no footage, no fallback
        import_points2d(
            _target(config), tmp_path, {"format": "deepfly3d", "keypoint_map": {0: "p0", 1: "p1"}}
        )
    with pytest.raises(ImportFormatError, match=r"keypoint '1' maps to 'nose'.*keypoint_map"):
        import_points2d(
            _target(config),
            tmp_path,
            {"format": "deepfly3d", "image_size": [10, 10], "keypoint_map": {0: "p0", 1: "nose"}},
        )
    _write_df3d_pickle(tmp_path / "df3d_result_2.pkl", np.full((2, 3, 2, 2), 0.5))
    with pytest.raises(ImportFormatError, match="matches 2 files"):
        import_points2d(_target(config), tmp_path, {"format": "deepfly3d", "image_size": [10, 10]})
    with pytest.raises(ImportFormatError, match="format"):
        import_points2d(_target(config), tmp_path, {"format": "openpose"})


# -- DeepLabCut / Lightning Pose CSV -------------------------------------------------

DLC_CSV = """scorer,DLC_resnet50,DLC_resnet50,DLC_resnet50,DLC_resnet50,DLC_resnet50,DLC_resnet50
bodyparts,head,head,head,tail,tail,tail
coords,x,y,likelihood,x,y,likelihood
0,10.5,20.25,0.99,30.0,40.0,0.2
1,11.5,21.25,0.95,,,
2,12.5,22.25,0.05,32.0,42.0,0.9
"""


def _write_views_csv(directory: Path, views, text=DLC_CSV) -> None:
    for v in views:
        (directory / f"{v}.csv").write_text(text)


def test_dlc_csv_import_with_map_and_threshold(tmp_path):
    views = ["a", "b"]
    _write_views_csv(tmp_path, views)
    spec = {
        "format": "dlc_csv",
        "keypoint_map": {"head": "p0", "tail": "p1"},
        "likelihood_threshold": 0.1,
        "image_size": [480, 960],
    }
    data = import_points2d(_target(rig_config(views, ["p0", "p1", "p2"])), tmp_path, spec)
    assert data.pts2d.shape == (2, 3, 3, 2)
    np.testing.assert_array_equal(data.pts2d[1, :2, 0], [[10.5, 20.25], [11.5, 21.25]])
    assert np.isnan(data.pts2d[:, 2, 0]).all()  # likelihood 0.05 < 0.1
    assert np.isnan(data.pts2d[:, 1, 1]).all()  # empty cells
    np.testing.assert_array_equal(data.pts2d[0, 2, 1], [32.0, 42.0])
    np.testing.assert_array_equal(data.conf[0, :, 0], [0.99, 0.95, np.nan])
    assert np.isnan(data.pts2d[:, :, 2]).all()  # p2: in no file
    assert data.image_sizes == {"a": (480, 960), "b": (480, 960)}


def test_dlc_csv_import_errors(tmp_path):
    views = ["a", "b"]
    config = rig_config(views, ["head", "p1"])
    _write_views_csv(tmp_path, ["a"])
    with pytest.raises(ImportFormatError, match=r"b\.csv.*pose2d\.import\.files"):
        import_points2d(_target(config), tmp_path, {"format": "dlc_csv", "image_size": [4, 4]})
    _write_views_csv(tmp_path, ["b"])
    with pytest.raises(ImportFormatError, match=r"a\.csv: keypoint 'tail' maps to 'tail'"):
        import_points2d(_target(config), tmp_path, {"format": "dlc_csv", "image_size": [4, 4]})
    # a deliberate drop is fine
    ok = import_points2d(
        _target(config),
        tmp_path,
        {"format": "dlc_csv", "image_size": [4, 4], "keypoint_map": {"tail": None}},
    )
    assert np.isfinite(ok.pts2d[:, :, 0]).all(-1).sum() == 6
    (tmp_path / "b.csv").write_text("\n".join(DLC_CSV.splitlines()[:-1]) + "\n")
    with pytest.raises(ImportFormatError, match="different frame counts"):
        import_points2d(
            _target(config),
            tmp_path,
            {"format": "dlc_csv", "image_size": [4, 4], "keypoint_map": {"tail": None}},
        )
    (tmp_path / "a.csv").write_text("frame,x,y\n0,1,2\n")
    with pytest.raises(ImportFormatError, match=r"a\.csv: not a DeepLabCut CSV"):
        read_dlc_csv(tmp_path / "a.csv")


def test_dlc_multi_animal_csv_needs_individual(tmp_path):
    text = (
        "scorer,S,S,S,S,S,S\n"
        "individuals,fly1,fly1,fly1,fly2,fly2,fly2\n"
        "bodyparts,head,head,head,head,head,head\n"
        "coords,x,y,likelihood,x,y,likelihood\n"
        "0,1,2,0.9,5,6,0.8\n"
    )
    path = tmp_path / "v.csv"
    path.write_text(text)
    with pytest.raises(ImportFormatError, match="individual"):
        read_dlc_csv(path)
    kp = read_dlc_csv(path, individual="fly2")
    assert kp.names == ["head"]
    np.testing.assert_array_equal(kp.xy[0, 0], [5.0, 6.0])
    assert kp.conf[0, 0] == 0.8


def test_dlc_export_imports_back_identically(tmp_path):
    rng = np.random.default_rng(0)
    views, points = ["a", "b", "c"], ["p0", "p1", "p2", "p3"]
    pts = rng.uniform(0, 960, size=(3, 6, 4, 2))
    conf = rng.uniform(0, 1, size=(3, 6, 4))
    pts[0, 2, 1] = np.nan
    conf[0, 2, 1] = np.nan
    pts[2, :, 3] = np.nan
    conf[2, :, 3] = np.nan
    files = write_dlc_views(tmp_path, pts, conf, views, points)
    assert [f.name for f in files] == ["a.csv", "b.csv", "c.csv"]
    header = files[0].read_text().splitlines()[:3]
    assert header[0].startswith("scorer,flylib") and header[1].startswith("bodyparts,p0,p0,p0,p1")
    assert header[2].startswith("coords,x,y,likelihood,x")
    back = import_points2d(
        _target(rig_config(views, points)),
        tmp_path,
        {"format": "lightning_pose", "image_size": [480, 960]},
    )
    np.testing.assert_array_equal(back.pts2d, pts)
    np.testing.assert_array_equal(back.conf, conf)


DATA = Path(__file__).resolve().parents[1] / "data" / "interop"


@pytest.mark.parametrize("name", ["dlc_table.h5", "dlc_fixed.h5"])
def test_dlc_h5_import_without_pytables(tmp_path, name):
    """Files written by pandas + PyTables (format "table" as DeepLabCut does, and "fixed"),
    holding the same numbers as DLC_CSV; read with h5py alone."""
    (tmp_path / "a.h5").write_bytes((DATA / name).read_bytes())
    (tmp_path / "a.csv").write_text(DLC_CSV)
    config = rig_config(["a"], ["head", "tail"])
    from_h5 = import_points2d(_target(config), tmp_path, {"format": "dlc_h5", "image_size": [4, 4]})
    from_csv = import_points2d(
        _target(config), tmp_path, {"format": "dlc_csv", "image_size": [4, 4]}
    )
    np.testing.assert_array_equal(from_h5.pts2d, from_csv.pts2d)
    np.testing.assert_array_equal(from_h5.conf, from_csv.conf)
    np.testing.assert_array_equal(from_h5.pts2d[0, 1, 0], [11.5, 21.25])
    assert np.isnan(from_h5.pts2d[0, 1, 1]).all()
    by_suffix = import_points2d(
        _target(config),
        tmp_path,
        {"format": "deeplabcut", "files": "{view}.h5", "image_size": [4, 4]},
    )
    np.testing.assert_array_equal(by_suffix.pts2d, from_h5.pts2d)


def test_dlc_h5_multi_animal(tmp_path):
    from flylib.interop import read_dlc_h5

    path = DATA / "dlc_multianimal_table.h5"
    with pytest.raises(ImportFormatError, match="individual"):
        read_dlc_h5(path)
    kp = read_dlc_h5(path, individual="fly2")
    assert kp.names == ["head", "tail"]
    np.testing.assert_array_equal(kp.xy[1], [[18.5, 19.5], [21.5, 22.5]])
    np.testing.assert_array_equal(kp.conf[:, 1], [11.5, 23.5])
    (tmp_path / "x.h5").write_bytes(b"not hdf5")
    with pytest.raises(ImportFormatError, match=r"x\.h5: not a readable "):
        read_dlc_h5(tmp_path / "x.h5")


# -- SLEAP analysis HDF5 -----------------------------------------------------------------


def _write_sleap(
    path: Path, locations: np.ndarray, scores: np.ndarray, nodes, transpose=True
) -> Path:
    """locations (T, K, 2, n_tracks), scores (T, K, n_tracks), as SLEAP's analysis export."""
    with h5py.File(path, "w") as f:
        f["node_names"] = np.array([n.encode() for n in nodes], dtype="S")
        f["track_names"] = np.array(
            [f"track_{i}".encode() for i in range(locations.shape[-1])], dtype="S"
        )
        f["tracks"] = locations.T if transpose else locations
        f["point_scores"] = scores.T if transpose else scores
    return path


@pytest.mark.parametrize("transpose", [True, False])
def test_sleap_analysis_import(tmp_path, transpose):
    rng = np.random.default_rng(1)
    loc = rng.uniform(0, 500, size=(5, 3, 2, 1))
    loc[2, 1] = np.nan
    scores = rng.uniform(0, 1, size=(5, 3, 1))
    for v in ("a", "b"):
        _write_sleap(tmp_path / f"{v}.analysis.h5", loc, scores, ["n0", "n1", "n2"], transpose)
    spec = {
        "format": "sleap",
        "image_size": [500, 500],
        "keypoint_map": {"n0": "p0", "n1": "p1", "n2": "p2"},
    }
    data = import_points2d(_target(rig_config(["a", "b"], ["p0", "p1", "p2"])), tmp_path, spec)
    np.testing.assert_array_equal(data.pts2d[1], loc[..., 0])
    expected_conf = np.where(np.isfinite(loc[..., 0]).all(-1), scores[..., 0], np.nan)
    np.testing.assert_array_equal(data.conf[0], expected_conf)


def test_sleap_several_tracks_need_a_choice(tmp_path):
    loc = np.arange(2 * 2 * 2 * 2, dtype=float).reshape(2, 2, 2, 2)
    _write_sleap(tmp_path / "a.analysis.h5", loc, np.ones((2, 2, 2)), ["p0", "p1"])
    config = rig_config(["a"], ["p0", "p1"])
    with pytest.raises(ImportFormatError, match="pose2d.import.track"):
        import_points2d(_target(config), tmp_path, {"format": "sleap", "image_size": [9, 9]})
    data = import_points2d(
        _target(config), tmp_path, {"format": "sleap", "image_size": [9, 9], "track": "track_1"}
    )
    np.testing.assert_array_equal(data.pts2d[0], loc[..., 1])


# -- calibrations --------------------------------------------------------------------------

ANIPOSE_TOML = """
[cam_0]
name = "left"
size = [1280, 1024]
matrix = [[1500.5, 0.0, 640.25], [0.0, 1490.0, 511.75], [0.0, 0.0, 1.0]]
distortions = [-0.12, 0.05, 0.001, -0.002, 0.01]
rotation = [0.1, -0.2, 0.05]
translation = [0.5, -0.25, 30.0]

[cam_1]
name = "right"
size = [1280, 1024]
matrix = [[1600.0, 0.0, 630.0], [0.0, 1610.0, 500.0], [0.0, 0.0, 1.0]]
distortions = [0.02, 0.0, 0.0, 0.0, 0.0]
rotation = [-0.3, 0.4, 0.1]
translation = [-1.5, 0.75, 28.0]

[metadata]
adjusted = false
"""


def _calibration_for(views=("left", "right"), **calibration) -> tuple[dict, tuple[str, ...]]:
    """A ``calibration`` table and the views (the config's cameras) it is read for."""
    return calibration, tuple(views)


def test_anipose_toml_projects_like_opencv(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(ANIPOSE_TOML)
    cams = load_calibration(*_calibration_for(file=str(path)))
    assert cams.names == ["left", "right"]
    pts = np.random.default_rng(2).uniform(-3, 3, size=(20, 3))
    ours = cams.project(pts)
    for i, table in enumerate(read_anipose_toml(path).values()):
        ref, _ = cv2.projectPoints(pts, table["rvec"], table["tvec"], table["kmat"], table["dist"])
        np.testing.assert_allclose(ours[i], ref[:, 0], rtol=0, atol=1e-9)


def test_anipose_toml_round_trip(tmp_path):
    src = tmp_path / "in.toml"
    src.write_text(ANIPOSE_TOML)
    cams = load_calibration(*_calibration_for(views=("right", "left"), file=str(src)))
    assert cams.names == ["right", "left"]  # matched by name, in config order
    out = write_anipose_toml(cams, tmp_path / "out.toml", {"right": (1024, 1280)})
    first, second = read_anipose_toml(src), read_anipose_toml(out)
    for name in ("left", "right"):
        for key in ("kmat", "dist", "rvec", "tvec"):
            np.testing.assert_allclose(second[name][key], first[name][key], rtol=0, atol=1e-12)
    assert second["right"]["size"] == (1280, 1024)
    assert second["left"]["size"] == (1280, 1024)  # no size given: 2 x principal point, rounded
    again = load_calibration(*_calibration_for(file=str(out)))
    np.testing.assert_allclose(again.rvecs, cams.subset(["left", "right"]).rvecs, atol=1e-12)


def test_anipose_toml_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    # the seed document's example puts (cx, cy) in K's last row: not a camera matrix
    bad.write_text(
        ANIPOSE_TOML.replace(
            "[0.0, 0.0, 1.0]]\ndistortions = [-0.12", "[1451.1, 993.0, 1.0]]\ndistortions = [-0.12"
        )
    )
    with pytest.raises(
        ImportFormatError,
        match=r"\[cam_0\] \(name 'left'\): 'matrix' is .*; it must be a 3x3 camera matrix",
    ):
        read_anipose_toml(bad)
    good = tmp_path / "good.toml"
    good.write_text(ANIPOSE_TOML)
    with pytest.raises(
        ImportFormatError, match=r"no camera for views \['centre'\].*calibration.names"
    ):
        load_calibration(*_calibration_for(views=("left", "centre"), file=str(good)))
    cams = load_calibration(
        *_calibration_for(views=("left", "centre"), file=str(good), names={"centre": "right"})
    )
    assert cams.names == ["left", "centre"] and cams.intrs[1, 0] == 1600.0


def test_calibrations_index_resolves_session(tmp_path):
    (tmp_path / "calibrations").mkdir()
    (tmp_path / "calibrations" / "session0.toml").write_text(ANIPOSE_TOML)
    (tmp_path / "calibrations" / "session1.toml").write_text(
        ANIPOSE_TOML.replace("1500.5", "1700.0")
    )
    (tmp_path / "calibrations.csv").write_text(
        ",file\n"
        "labeled-data/session0/img00000005.png,calibrations/session0.toml\n"
        "labeled-data/session0/img00000010.png,calibrations/session0.toml\n"
        "labeled-data/session1/img00000151.png,calibrations/session1.toml\n"
    )
    index = tmp_path / "calibrations.csv"
    assert calibration_from_index(index, "session1") == tmp_path / "calibrations" / "session1.toml"
    recording = tmp_path / "session1"
    recording.mkdir()
    cams = load_calibration(*_calibration_for(index=str(index)), recording)
    assert cams.intrs[0, 0] == 1700.0
    with pytest.raises(ImportFormatError, match="no row for session 'session7'"):
        calibration_from_index(index, "session7")
    # what the workflow lists as inputs of the rules that build this rig
    assert calibration_inputs(_calibration_for(index=str(index))[0], recording) == [
        index,
        tmp_path / "calibrations" / "session1.toml",
    ]
    assert calibration_inputs(_calibration_for(index=str(index))[0], tmp_path / "session7") == [
        index
    ]
    assert calibration_inputs(_calibration_for(file="calibrations/session0.toml")[0], tmp_path) == [
        tmp_path / "calibrations" / "session0.toml"
    ]  # relative to the recording
    assert calibration_inputs(_calibration_for(file=str(tmp_path / "absent.toml"))[0]) == []
    assert calibration_inputs(None) == []


def test_df3d_calibration_pickle_projects_like_opencv(tmp_path):
    rng = np.random.default_rng(3)
    calib = {"name": "df3d"}
    for i in range(3):
        rvec = rng.normal(scale=0.5, size=3)
        rmat, _ = cv2.Rodrigues(rvec)
        calib[i] = {
            "R": rmat,
            "tvec": rng.normal(size=3) + [0, 0, 50],
            "intr": np.array([[15000.0, 0, 480], [0, 15000.0, 240], [0, 0, 1]]),
            "distort": np.array([0.1, -0.05, 0.0, 0.001, 0.0]),
        }
    path = tmp_path / "calib.pkl"
    with path.open("wb") as fh:
        pickle.dump(calib, fh)
    cams = load_calibration(*_calibration_for(views=("x", "y", "z"), file=str(path)))
    assert cams.names == ["x", "y", "z"]
    pts = rng.uniform(-1, 1, size=(10, 3))
    ours = cams.project(pts)
    for i in range(3):
        c = calib[i]
        ref, _ = cv2.projectPoints(
            pts, cv2.Rodrigues(c["R"])[0], c["tvec"], c["intr"], c["distort"]
        )
        np.testing.assert_allclose(ours[i], ref[:, 0], rtol=0, atol=1e-8)


# -- exports ---------------------------------------------------------------------------------


def test_points3d_csv_one_row_per_frame_nan_when_missing(tmp_path):
    pts3d = np.arange(4 * 2 * 3, dtype=float).reshape(4, 2, 3)
    pts3d[1, 0] = np.nan
    err = np.full((3, 4, 2), np.nan)
    err[0, :, :] = 1.0
    err[1, :, :] = 3.0
    pts2d = np.where(np.isfinite(err)[..., None], 5.0, np.nan)
    path = write_points3d_csv(tmp_path / "p3d.csv", pts3d, ["a", "b"], err, pts2d)
    table = pd.read_csv(path)
    assert len(table) == 4 and table["fnum"].tolist() == [0, 1, 2, 3]
    assert list(table.columns[:12]) == [
        "a_x",
        "a_y",
        "a_z",
        "a_error",
        "a_ncams",
        "a_score",
        "b_x",
        "b_y",
        "b_z",
        "b_error",
        "b_ncams",
        "b_score",
    ]
    assert table.loc[1, ["a_x", "a_y", "a_z", "a_error", "a_score"]].isna().all()
    np.testing.assert_array_equal(table[["b_x", "b_y", "b_z"]].to_numpy(), pts3d[:, 1])
    assert (
        table.loc[0, "a_error"] == 2.0
        and table.loc[0, "a_ncams"] == 2
        and table.loc[0, "a_score"] == 1.0
    )
    frame = points3d_table(pts3d, ["a", "b"])
    assert frame["a_error"].isna().all() and frame["a_ncams"].isna().all()  # no 2D: Anipose's NaN


# -- integration with the default config and real footage -------------------------------------


def test_default_config_df3d_import_saves_as_pose2d_artifact(
    df3d_sample_dir, df3d_pickle, tmp_path
):
    from flylib.results import Pose2dData

    config = Config.default()
    data = import_points2d(import_target(config), df3d_sample_dir, {"format": "deepfly3d"})
    assert data.view_names == config.view_names()
    data.save(tmp_path / "pose2d.h5", config.skeleton())
    back = Pose2dData.load(tmp_path / "pose2d.h5")
    np.testing.assert_array_equal(back.pts2d, data.pts2d)
    assert back.image_sizes == data.image_sizes


def test_dlc_import_reads_sizes_and_checks_frames_against_footage(deeperfly_example_dir, tmp_path):
    """DeepLabCut's own file naming via {stem}; sizes and frame counts from the real videos."""
    views = RIG_VIEWS[:2]
    rng = np.random.default_rng(4)
    for i in range(2):
        write_dlc_views(
            tmp_path,
            rng.uniform(0, 400, (1, 64, 2, 2)),
            None,
            [f"camera_{i}DLC_resnet50_flyJan1shuffle1_1000"],
            ["p0", "p1"],
        )
    config = rig_config(views, ["p0", "p1"])
    spec = {"format": "deeplabcut", "files": str(tmp_path / "{stem}DLC_*.csv")}
    data = import_points2d(_target(config), deeperfly_example_dir, spec)
    assert data.image_sizes == {"rh": (480, 960), "rm": (480, 960)}
    assert data.pts2d.shape == (2, 64, 2, 2)
    for i in range(2):
        write_dlc_views(
            tmp_path,
            rng.uniform(0, 400, (1, 10, 2, 2)),
            None,
            [f"camera_{i}DLC_resnet50_flyJan1shuffle1_1000"],
            ["p0", "p1"],
        )
    with pytest.raises(
        ImportFormatError, match=r"camera_0DLC.*10 frames but view 'rh' footage has 64"
    ):
        import_points2d(_target(config), deeperfly_example_dir, spec)


def test_calibration_without_configured_views_takes_the_file_order(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(ANIPOSE_TOML)
    cams = load_calibration({"file": "calibration.toml"}, recording_dir=tmp_path)
    assert cams.names == ["left", "right"]


def test_import_spec_validation(tmp_path):
    config = rig_config(["a"], ["p0"])
    with pytest.raises(ImportFormatError, match=r"pose2d.import must be a mapping"):
        import_points2d(_target(config), tmp_path, None)  # no pose2d.import in the config
    with pytest.raises(
        ImportFormatError,
        match=r"pose2d.import.file: unknown key; did you mean 'files'\? \(known: ",
    ):
        import_points2d(_target(config), tmp_path, {"format": "dlc_csv", "file": "a.csv"})
    with pytest.raises(ImportFormatError, match=r"image_size must be \[height, width\]"):
        import_points2d(
            _target(config), tmp_path, {"format": "dlc_csv", "image_size": ["480", 960]}
        )
    with pytest.raises(ImportFormatError, match=r"placeholder"):
        import_points2d(_target(config), tmp_path, {"format": "dlc_csv", "files": "camera_*.csv"})


def test_footage_of_a_view_is_only_video_or_images_like_the_detector_sees_it(tmp_path):
    # a glob source pattern must not pick up DeepLabCut's CSV written beside the video
    from flylib import io
    from flylib.config.sources import footage_globs
    from flylib.interop.views import footage_files, read_frame_count, read_frame_size

    config = rig_config(["a", "b"])
    config["sources"] = [
        {"name": "vid_a", "filename": "camera_0*"},
        {"name": "vid_b", "filename": "cam_b/*"},
    ]
    with io.VideoWriter(tmp_path / "camera_0.mp4", fps=10) as writer:
        writer.write_frames(np.zeros((3, 32, 48, 3), np.uint8))
    (tmp_path / "camera_0DLC_resnet50_flyJan1shuffle1_1000.csv").write_text("scorer\n")
    (tmp_path / "cam_b").mkdir()
    for i in (10, 9, 8):  # natural order 8, 9, 10 (by text: 10, 8, 9)
        cv2.imwrite(str(tmp_path / "cam_b" / f"img{i}.png"), np.zeros((20, 30, 3), np.uint8))
    (tmp_path / "cam_b" / "notes.txt").write_text("not a frame")
    footage = footage_files(footage_globs(config), tmp_path)
    assert footage == {
        "a": [tmp_path / "camera_0.mp4"],
        "b": [tmp_path / "cam_b" / f"img{i}.png" for i in (8, 9, 10)],
    }
    assert read_frame_count(footage["a"]) == 3 and read_frame_count(footage["b"]) == 3
    assert read_frame_size(footage["a"][0]) == (32, 48)
    assert read_frame_size(footage["b"][0]) == (20, 30)


def test_calibration_mirror_mirrors_the_files_world_and_keeps_every_pixel(tmp_path):
    """``calibration: {mirror: true}`` (issue 36): the file's rig in mirrored world
    coordinates, so the same 2D triangulates to the mirror image."""
    from flylib.handedness import WORLD_MIRROR

    rng = np.random.default_rng(5)
    calib = {}
    for i in range(3):
        calib[i] = {
            "R": cv2.Rodrigues(rng.normal(scale=0.5, size=3))[0],
            "tvec": rng.normal(size=3) + [0, 0, 50],
            "intr": np.array([[15000.0, 0, 480], [0, 15000.0, 240], [0, 0, 1]]),
            "distort": np.array([0.1, -0.05, 0.002, 0.001, 0.0]),
        }
    path = tmp_path / "calib.pkl"
    with path.open("wb") as fh:
        pickle.dump(calib, fh)
    views = ("x", "y", "z")
    plain = load_calibration(*_calibration_for(views=views, file=str(path)))
    mirrored = load_calibration(*_calibration_for(views=views, file=str(path), mirror=True))
    unset = load_calibration(*_calibration_for(views=views, file=str(path), mirror=False))
    pts = rng.uniform(-1, 1, size=(10, 3))
    np.testing.assert_allclose(mirrored.project(pts @ WORLD_MIRROR), plain.project(pts), atol=1e-8)
    assert not np.allclose(mirrored.project(pts), plain.project(pts), atol=1.0)
    np.testing.assert_array_equal(unset.rvecs, plain.rvecs)
    pixels = plain.project(pts)
    np.testing.assert_allclose(mirrored.triangulate(pixels), pts @ WORLD_MIRROR, atol=1e-6)
