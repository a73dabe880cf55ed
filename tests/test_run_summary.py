"""The end-of-run table (flylib.run_summary) and the summary figure's note on views
without 2D."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flylib.run_summary import RunRecording, log_warnings, run_table
from flylib.visualization.summary import views_without_2d

TRUTH = {
    "median": 0.0565,
    "p95": 0.0627,
    "body_length": 2.97,
    "median_aligned": 0.0065,
    "reconstructed": 0.986,
}


def write_summary(outdir: Path, **extra) -> None:
    outdir.mkdir(parents=True, exist_ok=True)
    summary = {
        "frames": 60,
        "reconstructed_3d_fraction": 0.5,
        "reprojection_error_px": {"median": 0.789, "p95": 1.774},
        **extra,
    }
    (outdir / "summary.json").write_text(json.dumps(summary))


def test_table_rows_warnings_and_the_demo_truth_last(tmp_path):
    demo, real, failed = tmp_path / "demo", tmp_path / "real", tmp_path / "failed"
    write_summary(demo, error_vs_truth=TRUTH)
    write_summary(real)
    (real / "logs").mkdir()
    (real / "logs" / "visualization.log").write_text(
        "/x/specs.py:480: UserWarning: visualization.videos[0] (pose2d): the footage frame rate is "
        "0.2 fps, not plausible; writing at visualization.default_fps = 30 fps\n"
        "  warnings.warn(\n"
        "2026-01-01 10:00:00,000 WARNING flylib.io: camera_3.mp4: 2 frames short\n"
        "2026-01-01 10:00:00,000 INFO flylib.io: all good\n"
    )
    recs = [
        RunRecording("demo", demo, demo=True),
        RunRecording("real", real),
        RunRecording("failed", failed),
    ]
    lines = run_table(recs, failed=True).splitlines()
    assert lines[0].startswith("flylib: per-recording results (the run failed")
    assert lines[1].split() == ["recording", "frames", "in", "3D", "reproj", "px", "outputs"]
    assert lines[2].split() == ["demo", "60", "50.0%", "0.79", "/", "1.77", str(demo)]
    assert lines[3].split()[:2] == ["real", "60"]
    assert lines[4].split()[0] == "failed" and "no result yet" in lines[4]
    assert lines[5] == "warnings:"
    assert (
        "real: visualization: visualization.videos[0] (pose2d): the footage frame rate is 0.2 fps"
        in lines[6]
    )
    assert lines[7] == "  real: visualization: camera_3.mp4: 2 frames short"
    assert lines[-1].startswith("demo: 3D error against the demo truth: median 0.0565, p95 0.0627")
    assert len(lines) == 9
    # the columns line up under the header
    assert lines[2].index(str(demo)) == lines[1].index("outputs")


def test_suspect_column_appears_when_a_summary_counts_suspects(tmp_path):
    write_summary(tmp_path / "a", suspects=3)
    write_summary(tmp_path / "b", suspects={"count": 0, "frames": []})
    write_summary(tmp_path / "c")
    table = run_table([RunRecording(n, tmp_path / n) for n in "abc"]).splitlines()
    assert "suspects" in table[1].split()
    assert table[1].split()[-2:] == ["suspects", "outputs"]
    assert [row.split()[6] for row in table[2:5]] == ["3", "0", "-"]
    assert "suspects" not in run_table([RunRecording("c", tmp_path / "c")])


def test_log_warnings_are_distinct_and_named_by_log(tmp_path):
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "pose2d.log").write_text(
        "a.py:1: UserWarning: twice\na.py:1: UserWarning: twice\n"
    )
    assert log_warnings(tmp_path) == ["pose2d: twice"]
    assert log_warnings(tmp_path / "absent") == []


def test_summary_figure_names_the_views_without_2d(tmp_path):
    from flylib.camera.rig import CameraGroup
    from flylib.results import PoseResult
    from flylib.skeleton import Skeleton
    from flylib.visualization import summary_figure

    names = ["a", "b", "c"]
    pts2d = np.random.default_rng(0).uniform(0, 100, (3, 4, 2, 2))
    pts2d[1] = np.nan  # view b saw nothing
    assert views_without_2d(pts2d, names) == ["b"]
    assert views_without_2d(pts2d[[0, 2]], ["a", "c"]) == []
    cameras = CameraGroup.from_arrays(
        names,
        np.zeros((3, 3)),
        np.tile([0.0, 0.0, 10.0], (3, 1)),
        np.tile([100.0, 100.0, 50.0, 50.0], (3, 1)),
        np.zeros((3, 5)),
    )
    skeleton = Skeleton(point_names=("p0", "p1"), limbs={"leg": ("p0", "p1")}, palette={}, name="t")
    error = np.where(np.isfinite(pts2d).all(-1), 1.0, np.nan)
    result = PoseResult(
        cameras=cameras,
        skeleton=skeleton,
        pts2d=pts2d,
        pts3d=np.zeros((4, 2, 3)),
        reproj_error=error,
    )
    assert summary_figure(result, tmp_path / "s.png", dpi=30).stat().st_size > 0


def test_a_failed_run_does_not_show_an_earlier_runs_result(tmp_path):
    import os
    import time

    for name in ("failed", "untouched", "finished"):
        write_summary(tmp_path / name, error_vs_truth=TRUTH)
        (tmp_path / name / "logs").mkdir()
        os.utime(tmp_path / name / "summary.json", (1_000_000, 1_000_000))  # an earlier run
    start = time.time() - 1
    (tmp_path / "failed" / "logs" / "pose2d.log").write_text("error: x.csv: not a DeepLabCut CSV\n")
    (tmp_path / "finished" / "logs" / "assemble.log").write_text("ok\n")
    os.utime(tmp_path / "finished" / "summary.json")  # rewritten in this run
    recs = [RunRecording(n, tmp_path / n, demo=True) for n in ("failed", "untouched", "finished")]
    lines = run_table(recs, failed=True, since=start).splitlines()
    assert lines[2].split()[:2] == ["failed", "-"]
    assert f"failed: see {tmp_path / 'failed' / 'logs' / 'pose2d.log'}" in lines[2]
    assert lines[3].split()[:2] == ["untouched", "60"] and lines[4].split()[:2] == [
        "finished",
        "60",
    ]
    assert [line.split(":")[0] for line in lines[5:]] == ["untouched", "finished"]  # truth lines


def test_the_demo_truth_line_gives_the_triangulation_figure_beside_the_refined_one(tmp_path):
    demo = tmp_path / "demo"
    before = {**TRUTH, "median": 0.0701, "p95": 0.0812, "median_aligned": 0.0123}
    write_summary(demo, error_vs_truth=TRUTH, error_vs_truth_triangulation=before)
    last = run_table([RunRecording("demo", demo, demo=True)]).splitlines()[-1]
    assert last.startswith("demo: 3D error against the demo truth: median 0.0565")
    assert last.endswith(
        "(refined 3D; triangulation alone: median 0.0701, p95 0.0812, aligned 0.0123)"
    )


def _figures(median, p95, per_view=None):
    return {"held_out_px": {"median": median, "p95": p95, "n": 100}, "per_view": per_view or {}}


def _accuracy(tri, out, raw=None, kept=(), everywhere=False, per_view=None, frames=(60, 60)):
    points = {f"p{i}": {"median": 1.0, "p95": 2.0, "n": 10} for i in range(10)}
    return {
        "frames_evaluated": frames[0],
        "frames_total": frames[1],
        "triangulation": _figures(*tri),
        "refinement": _figures(*(raw or out)),
        "output": {**_figures(*out, per_view), "per_point": points},
        "kept_triangulation": list(kept),
        "kept_everywhere": everywhere,
        "output_stage": "refinement",
    }


def test_held_out_columns_mark_the_better_method_and_say_what_to_do(tmp_path):
    """The table explains when refinement is worse instead of bare numbers."""
    write_summary(tmp_path / "better", accuracy=_accuracy((5.87, 16.97), (4.1, 9.0)))
    write_summary(
        tmp_path / "partly",
        accuracy=_accuracy((5.87, 16.97), (5.78, 16.70), (5.95, 16.86), kept=["p1", "p2"]),
    )
    write_summary(
        tmp_path / "worse",
        accuracy=_accuracy(
            (5.87, 16.97),
            (5.87, 16.97),
            (7.51, 51.2),
            kept=[f"p{i}" for i in range(10)],
            everywhere=True,
            frames=(1000, 90000),
        ),
    )
    tri_only = {
        "frames_evaluated": 60,
        "frames_total": 60,
        "triangulation": _figures(2.0, 5.0),
        "output": _figures(2.0, 5.0),
        "output_stage": "triangulation",
    }
    write_summary(tmp_path / "tri", accuracy=tri_only)
    write_summary(tmp_path / "none")
    names = ["better", "partly", "worse", "tri", "none"]
    lines = run_table([RunRecording(n, tmp_path / n) for n in names]).splitlines()
    header = lines[1]
    assert "held-out tri" in header and "held-out ref" in header
    # the figures are right-aligned: a cell ends where its header ends
    col_tri = header.index("reproj px") + len("reproj px")
    col_ref = header.index("held-out tri") + len("held-out tri")
    end = header.index("held-out ref") + len("held-out ref")
    assert lines[2][col_tri:col_ref].strip() == "5.87 / 16.97"
    assert lines[2][col_ref:end].strip() == "4.10 / 9.00 *"
    assert lines[3][col_ref:end].strip() == "5.78 / 16.70 *"
    assert lines[4][col_tri:col_ref].strip() == "5.87 / 16.97"  # a tie marks nothing
    assert "*" not in lines[4] and lines[5][col_tri:col_ref].strip() == "2.00 / 5.00"
    assert lines[5][col_ref:end].strip() == "-" and lines[6].split()[6:8] == ["-", "-"]
    assert lines[7].startswith("accuracy: held-out px = median / p95 distance")
    said = dict(line.strip().split(": ", 1) for line in lines[8:12])
    assert said["better"].startswith(
        "refinement is better than triangulation (held-out median 5.87 -> 4.10 px"
    )
    assert "the refined 3D is used for 8 of the 10 points" in said["partly"]
    assert "for 2 (p1, p2) it predicted the held-out cameras worse" in said["partly"]
    assert "kept_triangulation" in said["partly"]
    assert said["worse"].startswith("refinement made this recording worse than triangulation")
    assert "7.51" in said["worse"] and "pipeline.do_refinement: false" in said["worse"]
    assert said["worse"].endswith(" Held out on 1000 of 90000 frames.")
    assert said["tri"].startswith("each camera is predicted from the others to median 2.00 px")
    assert len(lines) == 12


def test_points_no_held_out_camera_can_check_are_named_apart_from_the_worse_ones(tmp_path):
    """Issue 46: on a rig where points are seen by two cameras at most, nothing checks
    refinement there; the run says so instead of nothing (4 cameras) or "worse" (5)."""
    unchecked = {
        "frames_evaluated": 15,
        "frames_total": 15,
        "triangulation": {"held_out_px": {"median": None, "p95": None, "n": 0}},
        "output": {"held_out_px": {"median": None, "p95": None, "n": 0}, "per_point": {}},
        "kept_triangulation": ["p0", "p1"],
        "kept_everywhere": True,
        "output_stage": "refinement",
    }
    write_summary(tmp_path / "four", accuracy=unchecked)
    mixed = _accuracy((5.87, 16.97), (5.78, 16.70), kept=["p1", "p2"])
    mixed["output"]["per_point"] |= {"q0": {"median": None, "p95": None, "n": 0}}
    mixed["output"]["per_point"] |= {"q1": {"median": None, "p95": None, "n": 0}}
    write_summary(tmp_path / "five", accuracy=mixed)
    lines = run_table([RunRecording(n, tmp_path / n) for n in ("four", "five")]).splitlines()
    said = dict(line.strip().split(": ", 1) for line in lines[-2:])
    assert said["four"] == (
        "no held-out error: no point is seen by 3 cameras, so none can be rebuilt without one "
        "of them and checked against it; the images cannot measure the 3D's error, nor "
        "refinement's: the results keep the triangulation for every point"
    )
    assert "used for 8 of the 10 points that could be checked" in said["five"]
    assert "for 2 (p1, p2) it predicted the held-out cameras worse" in said["five"]
    assert said["five"].endswith(
        "2 points (q0, q1) are never seen by three cameras at once: no held-out camera checks them."
    )


def test_the_cameras_that_disagree_are_named(tmp_path):
    views = {
        v: {"median": m, "p95": 2 * m, "n": 9} for v, m in zip("abcdef", (14, 19, 10, 2, 1.6, 2))
    }
    write_summary(tmp_path / "r", accuracy=_accuracy((6.0, 20.0), (5.0, 18.0), per_view=views))
    line = run_table([RunRecording("r", tmp_path / "r")]).splitlines()[-1]
    assert "Cameras a 14.00 px, b 19.00 px, c 10.00 px disagree with the others" in line
    assert "mislabeled" in line


def test_a_killed_or_stopped_job_is_reported_as_such_never_as_failed_with_an_empty_log(tmp_path):
    import shutil
    import time

    from flylib.run_summary import JOB_FINISHED

    start = time.time() - 1
    logs = {
        "killed": {"pose2d.log": f"{JOB_FINISHED}\n", "refinement.log": ""},
        "signal": {"refinement.log": "INFO flylib.refinement: chunk 3 of 9\n"},
        "stopped": {"refinement.log": "INFO x: started\nstopped by SIGTERM\n"},
        "failed": {"pose2d.log": "error: x.csv: not a DeepLabCut CSV\n"},
        "halted": {"pose2d.log": f"{JOB_FINISHED}\n"},
        "deleted": {},
    }
    for name, files in logs.items():
        (tmp_path / name / "logs").mkdir(parents=True)
        for log, text in files.items():
            (tmp_path / name / "logs" / log).write_text(text)
    shutil.rmtree(tmp_path / "deleted")
    signal_log = tmp_path / "signal" / "logs" / "refinement.log"
    snakemake_log = tmp_path / "snakemake.log"
    snakemake_log.write_text(
        "CalledProcessError in file refinement.smk, line 29:\n"
        "Command 'python refinement.py' died with <Signals.SIGKILL: 9>.\n"
        "Error in rule refinement:\n"
        f"    log: {signal_log} (check log file(s) for error details)\n"
        "WorkflowError:\nOutput out/stages/pose2d.h5 has older modification time (2030) than "
        "input fly/camera_0.mp4 (2031). This could indicate a clock skew problem in your "
        "network and would trigger a rerun of this job in the next execution\n"
    )
    recs = [RunRecording(name, tmp_path / name) for name in logs]
    text = run_table(recs, failed=True, since=start, snakemake_log=[str(snakemake_log)])
    rows = dict(line.split(None, 1) for line in text.splitlines()[2:8])
    killed_log = tmp_path / "killed" / "logs" / "refinement.log"
    assert rows["killed"].endswith(
        f"(refinement was killed (SIGKILL or out of memory): its log {killed_log} ends "
        "without an error; re-run to resume)"
    )
    assert rows["signal"].endswith(
        f"(refinement was killed by SIGKILL: its log {signal_log} ends without an error; "
        "re-run to resume)"
    )
    assert rows["stopped"].endswith("(refinement was stopped by SIGTERM; re-run to resume)")
    assert rows["failed"].endswith(f"(failed: see {tmp_path / 'failed' / 'logs' / 'pose2d.log'})")
    assert "not finished: its last job (pose2d) ended well, then the run stopped" in rows["halted"]
    assert "its output folder was deleted during the run" in rows["deleted"]
    assert "failed: see" not in text.replace("failed: see " + str(tmp_path / "failed"), "")
    warnings = text.split("warnings:\n", 1)[1].splitlines()
    assert warnings[0].startswith("  snakemake: Output out/stages/pose2d.h5 has older")
    assert "clock skew" in warnings[0]


def test_the_table_fits_a_100_column_terminal(tmp_path):
    """Every column a run can show (held-out figures, suspects; a right-handed fly adds no handedness column), the real sample's
    figures and a short outdir (the table was 170 columns wide before)."""
    out = tmp_path / "fly7"
    write_summary(
        out,
        suspects=12,
        accuracy=_accuracy((5.87, 16.97), (5.78, 16.70)),
        handedness={"score": 0.96, "verdict": "right-handed", "message": None},
    )
    lines = run_table([RunRecording("fly7", out)]).splitlines()
    width = max(len(line) for line in lines[1:3]) - len(str(out))
    assert width + len("/results/fly7") <= 100, lines[1:3]


def test_a_mirror_image_is_flagged_in_its_row_and_explained_once_under_the_table(tmp_path):
    """Issue 36: the handedness column, and the cause and switch of a mirror image
    (assemble's warning says the same: it is not repeated among the warnings)."""
    message = (
        "the 3D is the fly's mirror image, its left legs on its right (handedness -0.96, "
        "median of 15 frames); the calibration file /d/calib.pkl gives a mirror-image world; "
        "set calibration: {mirror: true} in the config to mirror it back"
    )
    write_summary(
        tmp_path / "a",
        handedness={"score": -0.96, "verdict": "mirrored", "message": message},
    )
    write_summary(
        tmp_path / "b",
        handedness={"score": 0.95, "verdict": "right-handed", "message": None},
    )
    write_summary(tmp_path / "c")  # assembled before the check: no entry
    (tmp_path / "a" / "logs").mkdir()
    (tmp_path / "a" / "logs" / "assemble.log").write_text(
        f"2026-01-01 00:00:00 WARNING flylib.pipeline.assemble: {message}\n"
        "2026-01-01 00:00:00 WARNING flylib.x: another warning\n"
    )
    recordings = [RunRecording(name, tmp_path / name) for name in "abc"]
    lines = run_table(recordings).splitlines()
    assert lines[1].split()[-2:] == ["handedness", "outputs"]
    assert lines[2].split()[-3:-1] == ["-0.96", "MIRRORED"]
    assert lines[3].split()[-2] == "+0.95" and lines[4].split()[-2] == "-"
    at = lines.index("mirror image (the left legs on the fly's right):")
    assert lines[at + 1] == f"  a: {message}"
    assert lines[at + 2 :] == ["warnings:", "  a: assemble: another warning"]
