"""Corrected frames exported as DeepLabCut labeled data (``flylib export --training-data``),
read back with sleap-io's DeepLabCut reader and pandas' HDF5 reader (DeepLabCut's own
``CollectedData_<scorer>.h5`` key), not with flylib's code."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flylib.errors import ResultsError
from flylib.results import PoseResult

from gui_fixtures import make_corrected_outputs, make_demo_outputs

FRAMES = 12


@pytest.fixture(scope="module")
def corrected_run(tmp_path_factory):
    return make_corrected_outputs(tmp_path_factory.mktemp("training") / "rec", frames=FRAMES)


def test_export_is_read_back_by_sleap_io_and_pandas(corrected_run, tmp_path, capsys):
    import pandas as pd
    import sleap_io

    from flylib.cli import main

    out, (view_a, point_a, edit_xy), (view_b, point_b) = corrected_run
    result = PoseResult.load(out / "results.h5")
    views, points = list(result.cameras.names), list(result.skeleton.point_names)
    assert main(["export", str(out / "results.h5"), "--training-data", str(tmp_path)]) == 0
    assert "labeled-data folders" in capsys.readouterr().out
    folders = sorted((tmp_path / "labeled-data").iterdir())
    assert [f.name for f in folders] == [f"camera_{i}" for i in range(len(views))]

    # DeepLabCut's h5: key df_with_missing, columns (scorer, bodyparts, coords)
    table = pd.read_hdf(folders[view_a] / "CollectedData_flylib.h5", "df_with_missing")
    assert list(table.columns.names) == ["scorer", "bodyparts", "coords"]
    assert list(table.columns.get_level_values("bodyparts")[::2]) == points
    assert list(table.index) == [
        ("labeled-data", f"camera_{view_a}", "img0004.png"),
        ("labeled-data", f"camera_{view_a}", "img0007.png"),
    ]
    xy = table.loc[("labeled-data", f"camera_{view_a}", "img0004.png")]
    assert xy[("flylib", points[point_a], "x")] == pytest.approx(edit_xy[0])
    assert xy[("flylib", points[point_a], "y")] == pytest.approx(edit_xy[1])

    # sleap-io's DeepLabCut reader: the same labels and the frame images
    labels = sleap_io.load_dlc(str(folders[view_b] / "CollectedData_flylib.csv"))
    names = [node.name for node in labels.skeleton.nodes]
    assert sorted(names) == sorted(points)  # sleap-io orders the nodes its own way
    frames = sorted(labels.labeled_frames, key=lambda lf: lf.frame_idx)
    assert len(frames) == 2
    at7 = frames[1].instances[0].numpy()[[names.index(n) for n in points]]  # (P, 2)
    assert np.isnan(at7[point_b]).all()  # marked invisible: no label
    used = result.pts2d[view_b, 7]
    kept = np.isfinite(used).all(-1)
    np.testing.assert_allclose(at7[kept], used[kept], atol=1e-6)

    # the PNG is the footage frame
    png = cv2.imread(str(folders[view_b] / "img0007.png"))
    video = cv2.VideoCapture(str(out.parent / f"camera_{view_b}.mp4"))
    video.set(cv2.CAP_PROP_POS_FRAMES, 7)
    ok, frame = video.read()
    assert ok and png.shape == frame.shape
    assert np.abs(png.astype(int) - frame.astype(int)).mean() < 3


def test_labels_fill_a_dropped_detection_with_the_corrected_3d():
    from flylib.interop.training_data import training_labels

    used = np.full((2, 1, 3, 2), np.nan)
    given = np.full((2, 1, 3, 2), np.nan)
    ghost = np.zeros((2, 1, 3, 2)) + [[[[10.0, 20.0]]]]
    touched = np.zeros((2, 1, 3), bool)
    used[0, 0, 0] = (1.0, 2.0)  # kept: its own 2D
    given[0, 0, 0] = (1.0, 2.0)
    given[0, 0, 1] = (400.0, 300.0)  # dropped as an outlier: the reprojection
    given[1, 0, 0] = (5.0, 5.0)  # marked invisible by a person: nothing
    touched[1, 0, 0] = True
    ghost[1, 0, 2] = (-5.0, 3.0)  # outside the frame and never detected: nothing
    out = training_labels(used, given, ghost, touched, [(48, 64), (48, 64)])
    np.testing.assert_array_equal(out[0, 0, 0], (1.0, 2.0))
    np.testing.assert_array_equal(out[0, 0, 1], (10.0, 20.0))
    assert np.isnan(out[0, 0, 2]).all() and np.isnan(out[1, 0]).all()


def test_a_result_without_corrections_is_one_clear_error(tmp_path):
    from flylib.interop.training_data import export_training_data

    out = make_demo_outputs(tmp_path / "rec", frames=6)
    with pytest.raises(ResultsError, match="holds no corrections; correct frames in `flylib gui"):
        export_training_data(out / "results.h5", tmp_path / "dlc")
    assert not (tmp_path / "dlc").exists()


def test_export_into_a_dlc_project_merges_row_by_row_and_keeps_the_labs_labels(
    corrected_run, tmp_path, capsys
):
    """Issue 37 case 4: the lab's hand labels of other frames and body parts survive."""
    import pandas as pd

    from flylib.cli import main

    out, (view_a, point_a, edit_xy), _ = corrected_run
    points = list(PoseResult.load(out / "results.h5").skeleton.point_names)
    folder = tmp_path / "labeled-data" / f"camera_{view_a}"
    folder.mkdir(parents=True)
    # laid out as DeepLabCut writes it: scorer/bodyparts/coords rows, a 3-level index
    parts = [*points, "lab_only"]
    columns = pd.MultiIndex.from_product(
        [["lab"], parts, ["x", "y"]], names=["scorer", "bodyparts", "coords"]
    )
    rows = pd.MultiIndex.from_tuples(
        [("labeled-data", folder.name, n) for n in ("img0001.png", "img0004.png")]
    )
    lab = pd.DataFrame(
        np.arange(2 * 2 * len(parts), dtype=np.float64).reshape(2, -1), index=rows, columns=columns
    )
    lab.to_csv(folder / "CollectedData_lab.csv")
    lab.to_hdf(folder / "CollectedData_lab.h5", key="df_with_missing", mode="w")
    (folder / "img0004.png").write_bytes(b"the lab's own frame")
    before = (folder / "CollectedData_lab.csv").read_bytes()

    code = main(
        ["export", str(out / "results.h5"), "--training-data", str(tmp_path), "--scorer", "lab"]
    )
    assert code == 0
    said = capsys.readouterr().out
    assert (
        f"{folder / 'CollectedData_lab.csv'}: 1 frames added, 1 updated, 1 kept (backup: " in said
    )

    for table in (
        pd.read_hdf(folder / "CollectedData_lab.h5", "df_with_missing"),
        pd.read_csv(folder / "CollectedData_lab.csv", header=[0, 1, 2], index_col=[0, 1, 2]),
    ):
        assert list(table.columns.names) == ["scorer", "bodyparts", "coords"]
        assert list(table.columns) == list(lab.columns)
        assert [r[2] for r in table.index] == ["img0001.png", "img0004.png", "img0007.png"]
        # another frame: every label kept; the lab's own body part: kept in every frame
        pd.testing.assert_series_equal(
            table.iloc[0], lab.iloc[0], check_names=False, check_exact=True
        )
        assert (
            table.loc[rows[1], ("lab", "lab_only", "x")]
            == lab.loc[rows[1], ("lab", "lab_only", "x")]
        )
        assert np.isnan(table.iloc[2][("lab", "lab_only", "x")])
        # the corrected frame: flylib's edit
        assert table.loc[rows[1], ("lab", points[point_a], "x")] == pytest.approx(edit_xy[0])
        assert table.loc[rows[1], ("lab", points[point_a], "y")] == pytest.approx(edit_xy[1])
    backups = sorted(folder.glob("CollectedData_lab.csv.*.bak"))
    assert len(backups) == 1 and backups[0].read_bytes() == before
    assert len(list(folder.glob("CollectedData_lab.h5.*.bak"))) == 1
    assert (folder / "img0004.png").read_bytes() == b"the lab's own frame"
    assert (folder / "img0007.png").is_file()

    # again: nothing changes, nothing is rewritten or backed up again
    assert (
        main(
            ["export", str(out / "results.h5"), "--training-data", str(tmp_path), "--scorer", "lab"]
        )
        == 0
    )
    assert "unchanged (3 frames kept)" in capsys.readouterr().out
    assert len(list(folder.glob("CollectedData_lab.csv.*.bak"))) == 1


def test_an_older_projects_single_path_index_is_merged_in_its_own_layout(corrected_run, tmp_path):
    import pandas as pd

    out, (view_a, point_a, edit_xy), _ = corrected_run
    points = list(PoseResult.load(out / "results.h5").skeleton.point_names)
    folder = tmp_path / "labeled-data" / f"camera_{view_a}"
    folder.mkdir(parents=True)
    columns = pd.MultiIndex.from_product(
        [["lab"], points, ["x", "y"]], names=["scorer", "bodyparts", "coords"]
    )
    lab = pd.DataFrame(
        np.ones((1, 2 * len(points))),
        index=[f"labeled-data/{folder.name}/img0002.png"],
        columns=columns,
    )
    lab.to_csv(folder / "CollectedData_lab.csv")

    from flylib.cli import main

    assert (
        main(
            ["export", str(out / "results.h5"), "--training-data", str(tmp_path), "--scorer", "lab"]
        )
        == 0
    )
    table = pd.read_csv(folder / "CollectedData_lab.csv", header=[0, 1, 2], index_col=0)
    assert list(table.index) == [
        f"labeled-data/{folder.name}/{n}" for n in ("img0002.png", "img0004.png", "img0007.png")
    ]
    assert (table.iloc[0] == 1.0).all()
    assert table.iloc[1][("lab", points[point_a], "x")] == pytest.approx(edit_xy[0])
