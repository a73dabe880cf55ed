"""Sessions (flylib.sessions, issue 38): which recordings share a rig, and the session's
folder; the ``session`` key of a recordings entry and of the sheet."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from flylib.errors import ConfigError
from flylib.recordings import Recording, plan_listing
from flylib.sessions import SESSIONS_DIR, plan_sessions

SOURCES = [{"name": "left", "filename": "cam_0*"}]


def _rec(path: Path, rid: str, session: str | None = None, outdir: Path | None = None):
    return Recording(
        id=rid,
        path=path,
        sources={},
        outdir=outdir or path / "flylib_outputs",
        session=session,
    )


def test_recordings_of_one_folder_are_one_session_by_default(tmp_path):
    day1 = [_rec(tmp_path / "day1" / f"t{i}", f"t{i}") for i in range(3)]
    day2 = [_rec(tmp_path / "day2" / "t9", "t9")]
    sessions = plan_sessions([day1[0], day2[0], day1[1], day1[2]])
    assert [s.name for s in sessions] == ["day1", "day2"]
    assert sessions[0].ids == ["t0", "t1", "t2"]
    assert sessions[0].outdir == tmp_path / "day1" / SESSIONS_DIR / "day1"
    assert sessions[0].calibration == sessions[0].outdir / "calibration.toml"


def test_a_session_key_groups_across_folders_and_outdir_templates(tmp_path):
    out = tmp_path / "results"
    recs = [
        _rec(tmp_path / "a" / "t1", "t1", "fly3", out / "t1"),
        _rec(tmp_path / "b" / "t2", "t2", "fly3", out / "t2"),
        _rec(tmp_path / "a" / "t3", "t3", None, out / "t3"),
    ]
    sessions = plan_sessions(recs)
    assert [(s.name, s.ids) for s in sessions] == [("fly3", ["t1", "t2"]), ("a", ["t3"])]
    assert sessions[0].outdir == out / SESSIONS_DIR / "fly3"


def test_two_folders_of_one_name_are_two_sessions(tmp_path):
    recs = [_rec(tmp_path / "x" / "day" / "t1", "t1"), _rec(tmp_path / "y" / "day" / "t2", "t2")]
    sessions = plan_sessions(recs)
    assert len(sessions) == 2 and sessions[0].name != sessions[1].name
    assert all(s.name.startswith("day-") for s in sessions)
    assert len({s.outdir for s in sessions}) == 2


def test_a_session_folder_that_is_a_recordings_outdir_is_one_clear_error(tmp_path):
    clash = tmp_path / "day1" / SESSIONS_DIR / "day1"
    recs = [
        _rec(tmp_path / "day1" / "t1", "t1"),
        _rec(tmp_path / "day1" / "t3", "t3"),
        _rec(tmp_path / "other", "t2", outdir=clash),
    ]
    with pytest.raises(ConfigError, match="session 'day1'.*output folder of recording 't2'"):
        plan_sessions(recs)


def test_sheet_and_mapping_name_the_session(tmp_path):
    for name in ("t1", "t2"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "cam_0.mp4").write_bytes(b"")
    sheet = tmp_path / "recordings.tsv"
    sheet.write_text("path\tsession\nt1\tfly3\nt2\t\n")
    recs = plan_listing(str(sheet), SOURCES, check_frames=False)
    assert [r.session for r in recs] == ["fly3", None]
    recs = plan_listing(
        [{"path": str(tmp_path / "t1"), "session": "fly4"}, str(tmp_path / "t2")],
        SOURCES,
        check_frames=False,
    )
    assert [r.session for r in recs] == ["fly4", None]
    with pytest.raises(ConfigError, match=r"recordings\[0\]\.session: must be a name"):
        plan_listing([{"path": str(tmp_path / "t1"), "session": ["a"]}], SOURCES)


def test_a_session_folder_is_its_name_as_a_file_name(tmp_path):
    names = ["fly 3", "a__b", "日本", "Cafe\u0301", "fly 🐝"]
    recs = [_rec(tmp_path / "day" / f"t{i}", f"t{i}", n) for i, n in enumerate(names * 2)]
    folders = [s.outdir.name for s in plan_sessions(recs)]
    assert folders == ["fly_3", "a__b", "日本", "Caf\u00e9", "fly_u1f41d"]
    for bad in ("..", "a/b", "a\\b", "x\ny"):
        with pytest.raises(ConfigError, match=f"session {re.escape(repr(bad))} cannot be"):
            plan_sessions([_rec(tmp_path / "t", "t", bad)])
