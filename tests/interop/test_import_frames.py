"""Imported 2D lands on the frame the file names and its scores become confidences in
[0, 1] (issue 37, cases 10 and 11): DeepLabCut / Lightning Pose rows are placed by their
index (a frame number or a labelled image's path), gaps are missing, a frame given twice
is an error; likelihoods outside [0, 1] are refused, SLEAP and DeepFly3D scores clipped
with a warning naming the file. The workflow side is tests/workflow/test_imports.py."""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from flylib.config import Config
from flylib.errors import ImportFormatError
from flylib.interop import import_points2d, read_dlc_csv, read_dlc_h5
from flylib.interop.importer import as_confidences
from flylib.pipeline.pose2d import import_target

POINTS = ["head", "tail"]


def target(views=("a",)):
    data = {
        "sources": [{"name": f"vid_{v}", "filename": f"{v}.mp4"} for v in views],
        "cameras": {"defaults": {}, **{v: {} for v in views}},
        "skeleton": {"name": "test", "point_names": POINTS},
    }
    return import_target(Config.from_dict(data))


def dlc_frame(frames, seed=0) -> pd.DataFrame:
    """One row per entry of ``frames`` (the index), values drawn from ``seed``."""
    columns = pd.MultiIndex.from_product(
        [["s"], POINTS, ["x", "y", "likelihood"]], names=["scorer", "bodyparts", "coords"]
    )
    values = np.random.default_rng(seed).uniform(0.05, 0.95, size=(len(frames), 6))
    return pd.DataFrame(values, columns=columns, index=list(frames))


def expected(frame: pd.DataFrame, frames: list[int], n: int) -> np.ndarray:
    """``(n, 2, 2)`` xy with each row at its frame, NaN elsewhere."""
    xy = np.full((n, 2, 2), np.nan)
    values = frame.to_numpy().reshape(len(frame), 2, 3)[..., :2]
    xy[frames] = values
    return xy


def test_csv_rows_in_any_order_are_placed_by_their_frame_index(tmp_path):
    frame = dlc_frame([3, 0, 2, 1])
    frame.to_csv(tmp_path / "a.csv")
    kp = read_dlc_csv(tmp_path / "a.csv")
    np.testing.assert_array_equal(kp.xy, expected(frame, [3, 0, 2, 1], 4))
    data = import_points2d(target(), tmp_path, {"format": "dlc_csv", "image_size": [4, 4]})
    np.testing.assert_array_equal(data.pts2d[0], expected(frame, [3, 0, 2, 1], 4))


@pytest.mark.parametrize("split", [False, True], ids=["path", "three-columns"])
def test_labelled_data_rows_go_to_the_number_in_their_image_name_and_gaps_are_missing(
    tmp_path, split
):
    names = ["img047.png", "img003.png", "img005.png"]
    frame = dlc_frame(range(3))
    if split:  # DeepLabCut 2.2+: labeled-data, video, image in three index columns
        frame.index = pd.MultiIndex.from_tuples([("labeled-data", "cam", n) for n in names])
    else:
        frame.index = [f"labeled-data/cam/{n}" for n in names]
    frame.to_csv(tmp_path / "CollectedData_x.csv")
    kp = read_dlc_csv(tmp_path / "CollectedData_x.csv")
    assert kp.xy.shape == (48, 2, 2)
    np.testing.assert_array_equal(kp.xy, expected(frame, [47, 3, 5], 48))
    assert np.isnan(kp.conf[[0, 4, 46]]).all()


@pytest.mark.parametrize("layout", ["table", "fixed"])
def test_dlc_h5_rows_are_placed_by_the_pandas_index(tmp_path, layout):
    pytest.importorskip("tables")  # only to write the file; flylib reads it with h5py
    frame = dlc_frame([2, 0, 1])
    frame.to_hdf(tmp_path / "a.h5", key="df_with_missing", format=layout)
    np.testing.assert_array_equal(read_dlc_h5(tmp_path / "a.h5").xy, expected(frame, [2, 0, 1], 3))


def test_dlc_h5_labelled_data_index_is_read_as_image_numbers(tmp_path):
    pytest.importorskip("tables")
    frame = dlc_frame(range(3))
    frame.index = pd.MultiIndex.from_tuples(
        [("labeled-data", "cam", f"img{i:03d}.png") for i in (47, 3, 5)]
    )
    frame.to_hdf(tmp_path / "a.h5", key="df_with_missing")  # DeepLabCut's CollectedData
    np.testing.assert_array_equal(
        read_dlc_h5(tmp_path / "a.h5").xy, expected(frame, [47, 3, 5], 48)
    )


def test_a_frame_given_twice_is_an_error_naming_file_rows_and_index(tmp_path):
    dlc_frame([0, 1, 2, 1]).to_csv(tmp_path / "a.csv")
    with pytest.raises(ImportFormatError) as raised:
        read_dlc_csv(tmp_path / "a.csv")
    assert str(raised.value) == (
        f"{tmp_path / 'a.csv'}: frame 1 is given twice (data rows 2 and 4, index 1 and 1); "
        "keep one row per frame"
    )


def test_an_index_that_names_no_frame_is_an_error(tmp_path):
    frame = dlc_frame(range(2))
    frame.index = ["first", "second"]
    frame.to_csv(tmp_path / "a.csv")
    with pytest.raises(
        ImportFormatError, match=r"a\.csv: data row 1 has index 'first', which names no frame"
    ):
        read_dlc_csv(tmp_path / "a.csv")


def test_an_empty_or_fractional_index_is_an_error(tmp_path):
    frame = dlc_frame(range(2))
    frame.index = [0.0, 1.5]
    frame.to_csv(tmp_path / "a.csv")
    with pytest.raises(
        ImportFormatError, match=r"a\.csv: data row 2 has index 1\.5, which is no frame"
    ):
        read_dlc_csv(tmp_path / "a.csv")
    frame.index = [0.0, np.nan]
    frame.to_csv(tmp_path / "a.csv")
    with pytest.raises(
        ImportFormatError, match=r"a\.csv: data row 2 has index nan, which is no frame"
    ):
        read_dlc_csv(tmp_path / "a.csv")


def test_a_frame_index_past_any_recording_is_an_error_not_an_allocation(tmp_path):
    frame = dlc_frame(range(2))
    frame.index = ["0", "99999999999999999999999"]
    frame.to_csv(tmp_path / "a.csv")
    with pytest.raises(
        ImportFormatError, match=r"a\.csv: data row 2 names frame 9+, outside 0\.\.10000000"
    ):
        read_dlc_csv(tmp_path / "a.csv")


@pytest.mark.parametrize("fmt", ["dlc_csv", "lightning_pose", "deeplabcut"])
def test_a_likelihood_outside_0_1_is_refused_naming_the_file(tmp_path, fmt):
    frame = dlc_frame(range(3))
    frame.loc[1, ("s", "tail", "likelihood")] = 1000.0
    frame.to_csv(tmp_path / "a.csv")
    with pytest.raises(ImportFormatError) as raised:
        import_points2d(target(), tmp_path, {"format": fmt, "image_size": [4, 4]})
    assert str(raised.value).startswith(
        f"{tmp_path / 'a.csv'}: 1 score outside [0, 1], from 1000 to 1000 (first at frame 1, "
        "keypoint 'tail'); a DeepLabCut / Lightning Pose likelihood is a probability in [0, 1]"
    )


def test_a_likelihood_rounded_just_past_1_is_kept_as_1(tmp_path):
    frame = dlc_frame(range(2))
    frame.loc[0, ("s", "head", "likelihood")] = 1.0000001
    frame.to_csv(tmp_path / "a.csv")
    data = import_points2d(target(), tmp_path, {"format": "dlc_csv", "image_size": [4, 4]})
    assert data.conf[0, 0, 0] == 1.0


def _sleap(path: Path, scores: np.ndarray) -> None:
    """A one-track SLEAP analysis file (MATLAB layout) with ``scores`` ``(T, K)``."""
    locations = np.full((len(scores), 2, 2, 1), 1.5)
    with h5py.File(path, "w") as f:
        f["node_names"] = np.array([n.encode() for n in POINTS], dtype="S")
        f["tracks"] = locations.T
        f["point_scores"] = scores[..., None].T


def test_sleap_scores_above_1_are_clipped_with_a_warning_naming_the_file(tmp_path, caplog):
    _sleap(tmp_path / "a.analysis.h5", np.array([[0.5, 1.7], [1000.0, 0.25]]))
    with caplog.at_level(logging.WARNING):
        data = import_points2d(target(), tmp_path, {"format": "sleap", "image_size": [4, 4]})
    np.testing.assert_array_equal(data.conf[0], [[0.5, 1.0], [1.0, 0.25]])
    assert (
        f"{tmp_path / 'a.analysis.h5'}: 2 scores outside [0, 1], from 1.7 to 1000 (first at "
        "frame 0, keypoint 'tail'); SLEAP's point scores are not probabilities, so they are "
        "clipped into [0, 1]"
    ) in caplog.text


def test_sleap_scores_within_0_1_pass_without_a_word(tmp_path, caplog):
    _sleap(tmp_path / "a.analysis.h5", np.array([[0.5, 1.0], [0.0, 0.25]]))
    with caplog.at_level(logging.WARNING):
        data = import_points2d(target(), tmp_path, {"format": "sleap", "image_size": [4, 4]})
    np.testing.assert_array_equal(data.conf[0], [[0.5, 1.0], [0.0, 0.25]])
    assert "outside [0, 1]" not in caplog.text


def test_deepfly3d_heatmap_peaks_past_1_are_clipped_with_a_warning(caplog):
    conf = np.array([[[0.5, 1.3], [np.nan, -0.2]]])  # (cameras, frames, joints)
    with caplog.at_level(logging.WARNING):
        out = as_confidences(conf, "deepfly3d", Path("df3d_result.pkl"))
    np.testing.assert_array_equal(out, [[[0.5, 1.0], [np.nan, 0.0]]])
    assert "df3d_result.pkl: 2 scores outside [0, 1], from -0.2 to 1.3" in caplog.text
    assert "DeepFly3D's heatmap scores are not probabilities" in caplog.text
