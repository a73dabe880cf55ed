"""Sessions from a recordings sheet, through the real workflow (issue 45): a name is a
folder name, or refused before the DAG in one line; names that differ stay two sessions;
members of two frame sizes are refused by the dry run, the run and check-config alike; a
session of one recording runs; the dry run plans what the run does, a good run prints no
error text, and `flylib inspect` names the rig the run says the results use."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.scenarios.lab import flylib_cli
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


def _flylib(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return flylib_cli(cwd, *args)


def test_members_of_two_frame_sizes_are_refused_before_any_work(tmp_path):
    from flylib.config import Config
    from flylib.pipeline.demo import make_demo

    root = _sheet_workdir(tmp_path, ["rig", "rig"])
    # r2 filmed at half the resolution (a camera setting changed): a camera of half the
    # focal length in pixels keeps the fly in its 480x240 frames
    data = yaml.safe_load((root / "config.yaml").read_text())
    data["cameras"]["defaults"]["focal_length_px"] = [11194.0625, 11194.0625]
    for path in (root / "day" / "r2").iterdir():
        path.unlink()
    make_demo(Config.from_dict(data), root / "day" / "r2", frames=6, seed=2, height=240, width=480)
    line = (
        "invalid config: config.yaml: recordings (sheet recordings.tsv): session 'rig' is one "
        "rig, but r1's frames are 960x480 and r2's 480x240 (width x height); give r2 another "
        "session (its session key or sheet column), or footage of one size"
    )
    assert _refused(_run(root, "-n")) == line
    assert _refused(_run(root)) == line
    check = _flylib(root, "check-config", "config.yaml")
    assert check.returncode == 1, check.stdout + check.stderr
    assert check.stderr.strip() == f"flylib check-config: {line}"
    assert not list((root / "day").glob("*/flylib_*"))  # nothing started
    assert not (root / "day" / "flylib_sessions").exists()


def test_a_session_of_one_recording_runs_and_inspect_names_its_rig(tmp_path):
    root = _sheet_workdir(tmp_path, ["solo"])
    dry = _run(root, "-n")
    assert dry.returncode == 0, dry.stderr[-3000:]
    folder = root / "day" / "r1" / "flylib_sessions" / "solo"
    assert [f for rule, f in _jobs(dry) if rule == "session_calibration"] == [str(folder)]
    run = _run(root)
    assert run.returncode == 0, run.stderr[-3000:]
    assert not re.search(r"Exception|Error", run.stdout + run.stderr)
    # its rig is its own solve: the two rigs' held-out errors are equal, not one "better"
    said = re.search(r"^session solo .*$", run.stdout + run.stderr, re.M)
    assert said and re.fullmatch(
        r"session solo \(1 recording\): held-out median (\d+\.\d\d) px with each recording's "
        r"own rig, \1 px with the session's \(equal\); the rig the results use: "
        + re.escape(str(folder / "calibration.toml")),
        said[0],
    ), said
    results = root / "day" / "r1" / "flylib_outputs" / "results.h5"
    shown = _flylib(root, "inspect", str(results))
    assert shown.returncode == 0, shown.stderr[-3000:]
    assert f"rig: session solo's, solved over r1: {folder / 'calibration.toml'}" in (
        shown.stdout.splitlines()
    )
