"""DeepFly3D's two 2D layouts (0.x normalized, 1.x pixels), told apart from the data,
on the real files in ``../shared/data`` and on hand-made pickles of each layout."""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from flylib.errors import ImportFormatError
from flylib.interop import import_points2d
from flylib.interop.df3d import points2d_layout, read_df3d_calibration, read_df3d_points2d
from flylib.pipeline.pose2d import import_target

SIZE = (480, 960)  # (height, width) of DeepFly3D's frames


@pytest.fixture(scope="module")
def package_example(df3d_package_example_dir) -> Path:
    return df3d_package_example_dir


def _raw(path: Path) -> dict:
    with path.open("rb") as fh:
        return pickle.load(fh)  # the test's own trusted copy of DeepFly3D's file


def test_real_1x_result_is_read_as_pixels(package_example):
    raw = _raw(package_example / "df3d_result.pkl")["points2d"]
    assert points2d_layout(raw, np.tile(SIZE, (7, 1))) == "pixels"
    data = read_df3d_points2d(package_example / "df3d_result.pkl", [SIZE] * 7)
    missing = (raw == 0).all(-1)
    assert missing.any() and np.isnan(data.xy[missing]).all()
    np.testing.assert_array_equal(data.xy[~missing], raw[~missing])  # (x, y) as stored
    assert np.nanmax(data.xy[..., 0]) <= 960 and np.nanmax(data.xy[..., 1]) <= 480


def test_real_1x_result_agrees_with_its_own_calibration_and_3d(package_example):
    """The other side: DeepFly3D's own points3d, projected through its own calib.pkl
    (NumPy-integer keys) with OpenCV, lands on the 2D flylib read (side cameras)."""
    calib = read_df3d_calibration(package_example / "calib.pkl")
    assert sorted(calib) == list(range(7))
    in_result = read_df3d_calibration(package_example / "df3d_result.pkl")
    for c in range(7):
        np.testing.assert_array_equal(in_result[c]["kmat"], calib[c]["kmat"])
    data = read_df3d_points2d(package_example / "df3d_result.pkl", [SIZE] * 7)
    points3d = _raw(package_example / "df3d_result.pkl")["points3d"]
    for c in (0, 1, 2, 4, 5, 6):
        e = calib[c]
        proj, _ = cv2.projectPoints(
            points3d.reshape(-1, 3), e["rvec"], e["tvec"], e["kmat"], e["dist"]
        )
        proj = proj.reshape(data.xy.shape[1:])
        seen = np.isfinite(data.xy[c]).all(-1)
        error = np.linalg.norm(proj[seen] - data.xy[c][seen], axis=-1)
        assert np.median(error) < 5.0, (c, np.median(error))
        # the transposed reading (the 0.x order) would be hundreds of pixels off
        assert np.median(np.linalg.norm(proj[seen] - data.xy[c][seen][:, ::-1], axis=-1)) > 100


def test_real_1x_result_imports_through_the_config(package_example, tmp_path):
    from flylib.config import Config

    shutil.copy(package_example / "df3d_result.pkl", tmp_path / "df3d_result.pkl")
    data = import_points2d(
        import_target(Config.default()), tmp_path, {"format": "deepfly3d", "image_size": list(SIZE)}
    )
    assert data.pts2d.shape == (7, 15, 38, 2)
    assert np.nanmax(data.pts2d[..., 0]) <= 960 and np.nanmax(data.pts2d[..., 1]) <= 480
    assert 0.4 < np.isfinite(data.pts2d).all(-1).mean() < 0.7


def test_real_0x_result_is_still_normalized(df3d_pickle):
    raw = _raw(df3d_pickle)["points2d"]
    assert points2d_layout(raw, np.tile(SIZE, (7, 1))) == "normalized"
    data = read_df3d_points2d(df3d_pickle, [SIZE] * 7)
    seen = np.isfinite(data.xy).all(-1)
    np.testing.assert_allclose(data.xy[seen][:, 0], raw[seen][:, 1] * 960)
    np.testing.assert_allclose(data.xy[seen][:, 1], raw[seen][:, 0] * 480)


def _pickle(path: Path, points2d: np.ndarray) -> Path:
    with path.open("wb") as fh:
        pickle.dump({"points2d": points2d}, fh)
    return path


def test_hand_made_pixel_pickle_keeps_x_y_and_drops_zero_zero(tmp_path):
    pts = np.zeros((2, 3, 2, 2))
    pts[:, :, 0] = [700.0, 200.0]  # x, y
    pts[1, 1, 1] = [0.5, 300.0]  # a point at the very left edge is still a point
    data = read_df3d_points2d(_pickle(tmp_path / "r.pkl", pts), [SIZE] * 2)
    np.testing.assert_array_equal(data.xy[:, :, 0], np.broadcast_to([700.0, 200.0], (2, 3, 2)))
    np.testing.assert_array_equal(data.xy[1, 1, 1], [0.5, 300.0])
    assert np.isnan(data.xy[0, :, 1]).all() and np.isnan(data.xy[1, [0, 2], 1]).all()


def test_mixed_layouts_are_one_error_naming_the_file(tmp_path):
    pts = np.zeros((2, 3, 2, 2))
    pts[0, :, 0] = [0.25, 0.5]  # normalized
    pts[1, :, 0] = [700.0, 200.0]  # pixels
    path = _pickle(tmp_path / "merged.pkl", pts)
    with pytest.raises(ImportFormatError, match=r"merged\.pkl: 'points2d' is ambiguous") as err:
        read_df3d_points2d(path, [SIZE] * 2)
    assert "\n" not in str(err.value)


def test_pixels_beyond_the_frame_are_one_error(tmp_path):
    pts = np.zeros((1, 2, 1, 2))
    pts[0, :, 0] = [460800.0, 12.0]
    path = _pickle(tmp_path / "big.pkl", pts)
    with pytest.raises(ImportFormatError, match=r"big\.pkl: .*camera 0.*outside its 960x480"):
        read_df3d_points2d(path, [SIZE])
