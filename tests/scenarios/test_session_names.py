"""Session names from a recordings sheet, through the real workflow (issue 45): a name
is a folder name, or refused before the DAG in one line; names that differ stay two
sessions; the dry run plans what the run does, and a good run prints no error text."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from tests.scenarios.test_path_names import REPO, _refused, _run

pytestmark = pytest.mark.slow  # runs Snakemake


def _sheet_workdir(root: Path, sessions: list[str]) -> Path:
    """``root/day/r1..`` (tiny imported-2D recordings), a sheet giving recording ``i`` the
    session ``sessions[i]``, a config with session calibration on, and the lab's own
    ``day/calibration.toml``."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    data["bundle_adjustment"].update(max_nfev=20, session=True)
    data["pipeline"].update(do_visualization=False, do_kinematics=False)
    cfg = Config.from_dict(data)
    spec = demo_import_spec(cfg)
    files = ";".join(f"{view}={name}" for view, name in spec["files"].items())
    rows = ["path\tsession\timport_format\timport_files"]
    for i, session in enumerate(sessions, 1):
        make_demo(cfg, root / "day" / f"r{i}", frames=6, seed=i)
        rows.append(f"day/r{i}\t{session}\t{spec['format']}\t{files}")
    (root / "recordings.tsv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    data["recordings"] = "recordings.tsv"
    (root / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True))
    (root / "day" / "calibration.toml").write_text("# the lab's own rig\n")
    return root


def _jobs(proc) -> list[tuple[str, str]]:
    """``(rule, its folder's wildcard)`` of each job a dry run lists."""
    text = proc.stdout + proc.stderr
    block = r"^[ \t]*(?:local)?rule (\w+):\n(?:[ \t]+.*\n)*?[ \t]+wildcards: \w+=(\S+)"
    return re.findall(block, text, re.M)  # a group job's jobs are indented


def test_a_session_named_dot_dot_is_refused_and_the_labs_rig_is_kept(tmp_path):
    root = _sheet_workdir(tmp_path, ["..", ".."])
    line = _refused(_run(root))
    assert line == (
        "recordings (sheet recordings.tsv): session '..' cannot be a folder name: it is "
        "made of dots only (. and .. are folders that exist); rename it (e.g. day1)"
    )
    assert (root / "day" / "calibration.toml").read_text() == "# the lab's own rig\n"
    assert not (root / "day" / "r1" / "flylib_outputs").exists()


def test_two_names_of_one_folder_are_refused_with_both_named(tmp_path):
    root = _sheet_workdir(tmp_path, ["fly 1", "Fly_1", "fly 1", "Fly_1"])
    line = _refused(_run(root, "-n"))
    assert line == (
        "recordings: sessions 'fly 1' and 'Fly_1' would both be solved in "
        f"{root / 'day' / 'flylib_sessions' / 'Fly_1'} (a session's name is its folder's, "
        "as a file name and ignoring case); rename one of them"
    )


def test_japanese_and_chinese_sessions_are_two_solves_planned_as_run(tmp_path):
    from flylib.results import read_meta

    root = _sheet_workdir(tmp_path, ["日本", "日本", "中国", "中国"])
    sessions = root / "day" / "flylib_sessions"
    dry = _run(root, "-n")
    assert dry.returncode == 0, dry.stderr[-3000:]
    solves = [folder for rule, folder in _jobs(dry) if rule == "session_calibration"]
    assert sorted(solves) == sorted(str(sessions / n) for n in ("日本", "中国"))
    run = _run(root)
    assert run.returncode == 0, run.stderr[-3000:]
    for proc in (dry, run):  # a good run says nothing of errors
        assert not re.search(r"Exception|Error", proc.stdout + proc.stderr)
    for name, members in (("日本", ("r1", "r2")), ("中国", ("r3", "r4"))):
        meta = read_meta(sessions / name / "session_calibration.h5")
        assert meta["session"] == {"name": name, "members": list(members)}
        for rec in members:
            tri = read_meta(root / "day" / rec / "flylib_outputs" / "stages" / "triangulation.h5")
            assert tri["upstream_artifact_ids"]["bundle_adjustment"] == meta["artifact_id"]
    assert sorted(p.name for p in sessions.iterdir()) == sorted(["日本", "中国"])
    assert (root / "day" / "calibration.toml").read_text() == "# the lab's own rig\n"

    # r2 moves to 中国: both solves again (日本 now of one recording), and r2's stages
    # that read the rig
    sheet = root / "recordings.tsv"
    sheet.write_text(sheet.read_text(encoding="utf-8").replace("r2\t日本", "r2\t中国"), "utf-8")
    moved = _run(root, "-n")
    assert moved.returncode == 0, moved.stderr[-3000:]
    jobs = {(rule, Path(folder).name) for rule, folder in _jobs(moved)}
    assert {j for j in jobs if j[0] == "session_calibration"} == {
        ("session_calibration", "日本"),
        ("session_calibration", "中国"),
    }
    assert {rule for rule, folder in _jobs(moved) if Path(folder).parent.name == "r2"} >= {
        "triangulation",
        "refinement",
        "assemble",
    }
