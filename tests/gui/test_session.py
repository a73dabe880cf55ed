"""Where ``flylib gui`` finds a recording's footage: a relative recording path from any
directory (the absolute path recorded beside it), ``--footage-dir``, and what the page
is told when footage is missing."""

from __future__ import annotations

import shutil

import h5py
import pytest

from flylib.errors import FootageError
from flylib.gui import ReviewSession
from flylib.results import read_meta_from

from gui_fixtures import make_demo_outputs


@pytest.fixture(scope="module")
def relative_run(tmp_path_factory):
    """A demo run whose recording path is relative ('rec', from the run's directory)."""
    root = tmp_path_factory.mktemp("gui_footage")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        out = make_demo_outputs(root / "rec", frames=6, recording_dir=type(root)("rec"))
    return root, out


def test_results_record_the_absolute_recording_path_beside_the_relative_one(relative_run):
    root, out = relative_run
    with h5py.File(out / "results.h5", "r") as f:
        meta = read_meta_from(f)
    assert meta["recording"] == "rec"
    assert meta["recording_abspath"] == str((root / "rec").resolve())


def test_relative_recording_found_from_another_directory(relative_run, tmp_path, monkeypatch):
    root, out = relative_run
    # the output directory moved elsewhere too: only the recorded absolute path leads back
    moved = tmp_path / "elsewhere" / "flylib_outputs"
    shutil.copytree(out, moved)
    monkeypatch.chdir(tmp_path)
    session = ReviewSession(moved)
    try:
        assert session.footage_missing == ""
        assert all(session.frames[v].has_footage for v in session.view_names)
        assert session.meta()["footage_missing"] == ""
    finally:
        session.close()


def test_missing_footage_is_named_and_footage_dir_finds_it(relative_run, tmp_path, monkeypatch):
    root, out = relative_run
    recording = tmp_path / "rec"
    shutil.copytree(root / "rec", recording)
    videos = tmp_path / "videos"
    videos.mkdir()
    for video in recording.glob("*.mp4"):
        video.rename(videos / video.name)
    monkeypatch.chdir(tmp_path)
    # the relative 'rec' now leads to a recording without its videos
    (root / "rec").rename(root / "rec-away")
    try:
        session = ReviewSession(recording / "flylib_outputs")
        try:
            message = session.meta()["footage_missing"]
            assert message.startswith("no footage for every view: not found in the recording ")
            assert "'rec'" in message and str(tmp_path / "rec") in message
            assert "--footage-dir DIR" in message
            assert not any(session.frames[v].has_footage for v in session.view_names)
        finally:
            session.close()
        session = ReviewSession(recording / "flylib_outputs", footage_dir=videos)
        try:
            assert session.footage_missing == ""
            assert all(session.frames[v].has_footage for v in session.view_names)
        finally:
            session.close()
    finally:
        (root / "rec-away").rename(root / "rec")
    with pytest.raises(FootageError, match=r"^--footage-dir .*nowhere: no such directory"):
        ReviewSession(recording / "flylib_outputs", footage_dir=tmp_path / "nowhere")


def test_review_marks_and_a_drag_replayed_counted_as_save_counts(tmp_path):
    """Unsaved review marks survive a restart (the journal); the replay notice counts
    the points a drag's many journal lines changed, as the Save button does."""
    out = make_demo_outputs(tmp_path / "rec", frames=6)
    session = ReviewSession(out)
    try:
        item = session.review_items[0]
        for frame in item["frames"]:
            session.edit("reviewed", frame, item["point"])
        xy = session.points(1)["views"][0]["points2d"]
        p = next(i for i, v in enumerate(xy) if v is not None)
        for step in range(5):  # one drag: five positions, one point
            session.edit("move", 1, p, session.view_names[0], [xy[p][0] + step, xy[p][1]])
        assert session.review()["done"] >= 1
    finally:
        session.close()  # killed before saving: the journal keeps it all
    session = ReviewSession(out)
    try:
        assert session.corrections.reviewed[item["frames"], item["point"]].all()
        assert session.notice.startswith(
            f"1 unsaved edit(s) and {len(item['frames'])} review mark(s) replayed from "
        )
        steps = 5 + len(item["frames"])
        assert f"stopped before saving, {steps} journal steps)" in session.notice
        assert session.meta()["notice"] == session.notice
        assert session.review()["done"] >= 1
    finally:
        session.close()
    session = ReviewSession(out)
    try:
        with pytest.raises(ValueError, match="unknown edit 'approve'; use .* or unreviewed$"):
            session.edit("approve", 0, 0)
    finally:
        session.close()
