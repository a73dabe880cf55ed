"""Suspect detection: the demo's injected gross outliers are found, clean data is quiet,
and each reason fires on the case it describes."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

from flylib.config import Config
from flylib.demo import load_truth, synthetic_fly
from flylib.pipeline.demo import demo_import_spec, make_demo
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.planning import config_rig
from flylib.pipeline.pose2d import run_pose2d
from flylib.pipeline.stage_helpers import run_inputs
from flylib.pipeline.triangulation import run_triangulation
from flylib.results import Pose2dData, read_stage
from flylib.suspects import SUSPECTS_FILE, find_suspects

FRAMES = 60


def triangulated_demo(directory, **settings):
    config = Config.default()
    make_demo(config, directory, frames=FRAMES, **settings)
    run_pose2d(
        stage_inputs(config, "pose2d"),
        directory,
        directory / "pose2d.h5",
        import_spec=demo_import_spec(config),
    )
    run_triangulation(
        run_inputs(config, "triangulation"),
        directory / "pose2d.h5",
        directory / "triangulation.h5",
    )
    pose2d = Pose2dData.load(directory / "pose2d.h5")
    tri = read_stage(directory / "triangulation.h5", "triangulation")
    suspects = find_suspects(
        tri["points3d"],
        tri["points"],
        tri["reproj_error"],
        config.skeleton().bones,
        pts2d_input=pose2d.pts2d,
    )
    return pose2d, tri, load_truth(directory / "truth.h5"), suspects


@pytest.mark.slow
@pytest.mark.parametrize("seed,outliers", [(0, 0.01), (1, 0.03)])
def test_suspects_hold_the_injected_outliers_that_reach_the_3d(tmp_path, seed, outliers):
    pose2d, tri, truth, suspects = triangulated_demo(tmp_path, seed=seed, outliers=outliers)
    # the demo moves an outlier 40-120 px off the true projection; noise is 1 px
    injected = np.nan_to_num(np.linalg.norm(pose2d.pts2d - truth["points2d"], axis=-1)) > 20
    reached = injected & np.isfinite(tri["points3d"]).all(-1)[None]  # (V, T, P)
    _, frames, points = np.nonzero(reached)
    assert len(frames) > 20
    flagged = np.zeros(reached.shape[1:], bool)
    flagged[suspects.frame, suspects.point] = True
    assert flagged[frames, points].mean() >= 0.8
    # those the robust fit kept (they bend the 3D) are found too
    _, kf, kp = np.nonzero(injected & np.isfinite(tri["points"]).all(-1))
    assert flagged[kf, kp].mean() >= 0.8


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 3])
def test_clean_data_flags_under_5_percent_of_frames(tmp_path, seed):
    *_, suspects = triangulated_demo(tmp_path, seed=seed, outliers=0.0)
    assert len(suspects.frames) < 0.05 * FRAMES


def clean_case(frames=40):
    """Exact 3D of the synthetic fly and its exact 2D through the default rig."""
    config = Config.default()
    views = config.view_names()
    cameras = config_rig(config, image_sizes={v: (480, 960) for v in views})
    pts3d = synthetic_fly(frames, seed=2)
    from flylib.demo import view_visibility

    vis = view_visibility(
        (config.data.get("pose2d") or {}).get("output_points"),
        views,
        list(config.skeleton().point_names),
    )
    pts2d = np.where(vis[:, None, :, None], cameras.project(pts3d), np.nan)
    pts2d = pts2d + np.random.default_rng(0).normal(0, 0.5, pts2d.shape)
    error = np.linalg.norm(cameras.project(pts3d) - pts2d, axis=-1)
    return config, cameras, pts3d, pts2d, error


def test_each_reason_fires_on_its_case():
    config, _, pts3d, pts2d, error = clean_case()
    bones = config.skeleton().bones
    quiet = find_suspects(pts3d, pts2d, error, bones, pts2d_input=pts2d)
    assert len(quiet) == 0 and not quiet.frame_score.any()
    names = list(config.skeleton().point_names)
    claw, tarsus = names.index("lf_claw"), names.index("lf_tibia_tarsus")
    moved = pts3d.copy()
    moved[10, claw] += [0.0, 0.0, 0.25]  # a claw 0.25 units off for one frame
    err = error.copy()
    seen = np.flatnonzero(np.isfinite(pts2d[:, 20, tarsus, 0]))
    err[seen[0], 20, tarsus] = 40.0  # a 40 px reprojection error
    given = pts2d.copy()
    used = pts2d.copy()
    used[seen[1], 30, tarsus] = np.nan  # dropped by the robust fit
    found = find_suspects(moved, used, err, bones, pts2d_input=given, point_names=names)
    by_pair = {(r["frame"], r["point"]): r["reasons"] for r in found.records()}
    assert {"jump", "bone_length"} <= set(by_pair[(10, claw)])
    assert "reprojection" in by_pair[(20, tarsus)]
    assert by_pair[(30, tarsus)] == ["ransac_drop"]
    assert found.frame_score[10] >= 1 and found.frame_score[5] == 0
    # a two-view point alone is not a suspect; with another reason it is
    two = pts2d.copy()
    seen = np.flatnonzero(np.isfinite(two[:, 15, tarsus, 0]))
    assert len(seen) > 2
    two[seen[2:], 15, tarsus] = np.nan
    alone = find_suspects(pts3d, two, error, bones)
    assert (15, tarsus) not in {(r["frame"], r["point"]) for r in alone.records()}
    # corrected points are a person's call: never suspects
    assert (10, claw) not in {
        (r["frame"], r["point"])
        for r in find_suspects(
            moved,
            used,
            err,
            bones,
            pts2d_input=given,
            corrected=np.eye(1, 38 * 40, 10 * 38 + claw, dtype=bool).reshape(40, 38),
        ).records()
    }


@pytest.mark.slow
def test_assemble_writes_suspects_csv_and_count_and_inspect_prints_it(tmp_path, capsys):
    from flylib.cli import main

    from gui_fixtures import make_demo_outputs

    out = make_demo_outputs(tmp_path / "rec", frames=20)
    summary = json.loads((out / "summary.json").read_text())
    with open(out / SUSPECTS_FILE) as fh:
        rows = list(csv.DictReader(fh))
    assert summary["suspects"] == len(rows) > 0
    assert set(rows[0]) == {"item", "frame", "point", "point_name", "score", "reasons", "detail"}
    assert all(0 <= int(r["frame"]) < 20 and float(r["score"]) >= 1 for r in rows)
    # in the order to review them: item 0 first, its best pair the recording's best
    items = [int(r["item"]) for r in rows]
    assert items == sorted(items) and items[0] == 0
    assert float(rows[0]["score"]) == max(float(r["score"]) for r in rows)
    assert not any(" view(s) " in r["detail"] for r in rows)
    # views numbered as frames and points are (0-based, issue 36), each with its camera
    from flylib.results import PoseResult

    cameras = list(PoseResult.load(out / "results.h5").cameras.names)
    named = [
        (int(i), name) for r in rows for i, name in re.findall(r"(\d+) \((\w+)\)", r["detail"])
    ]
    assert named and all(cameras[i] == name for i, name in named)
    assert not re.search(r"view \d+ [a-z]", " ".join(r["detail"] for r in rows))
    assert main(["inspect", str(out / "results.h5")]) == 0
    printed = capsys.readouterr().out
    assert f"suspects: {len(rows)} (frame, point) pairs" in printed
    assert f"{max(items) + 1} items" in printed


def _truth_pairs(pose2d, tri, truth, bones):
    """(T, P) pairs a person should look at: an injected 2D outlier in some view (the
    demo moves it 40-120 px, noise is 1 px), or a 3D more than 10% of a bone off."""
    injected = np.nan_to_num(np.linalg.norm(pose2d.pts2d - truth["points2d"], axis=-1)) > 20
    off3d = np.linalg.norm(tri["points3d"] - truth["points3d"], axis=-1)
    t3 = truth["points3d"]
    bone = np.median(np.linalg.norm(t3[:, bones[:, 0]] - t3[:, bones[:, 1]], axis=-1))
    return injected.any(axis=0), np.nan_to_num(off3d) > 0.1 * bone


@pytest.mark.slow
@pytest.mark.parametrize("seed,outliers", [(0, 0.01), (1, 0.03)])
def test_precision_recall_and_ranking_against_the_injected_errors(tmp_path, seed, outliers):
    pose2d, tri, truth, suspects = triangulated_demo(tmp_path, seed=seed, outliers=outliers)
    bones = Config.default().skeleton().bones
    injected, off3d = _truth_pairs(pose2d, tri, truth, bones)
    wanted = injected | off3d
    flagged = np.zeros_like(wanted)
    flagged[suspects.frame, suspects.point] = True
    precision = wanted[flagged].mean()
    recall = flagged[wanted].mean()
    assert precision >= 0.9 and recall >= 0.9, (precision, recall)
    # the items whose 3D is wrong come first
    items = suspects.items()
    bad_items = [i for i, it in enumerate(items) if off3d[it["frames"], it["point"]].any()]
    assert bad_items and max(bad_items) < len(bad_items) + 2, bad_items
    assert flagged[off3d].all()


def test_a_wrong_point_makes_no_suspects_of_its_neighbours():
    config, _, pts3d, pts2d, error = clean_case()
    bones = config.skeleton().bones
    names = list(config.skeleton().point_names)
    claw, femur_tibia = names.index("lf_claw"), names.index("lf_femur_tibia")
    moved = pts3d.copy()
    moved[10, claw] += [0.0, 0.0, 0.25]  # a leaf point, one frame
    moved[20, femur_tibia] += [0.0, 0.25, 0.0]  # a middle joint, two bones
    found = find_suspects(moved, pts2d, error, bones, pts2d_input=pts2d, point_names=names)
    pairs = {(int(t), int(p)) for t, p in zip(found.frame, found.point)}
    assert pairs == {(10, claw), (20, femur_tibia)}, sorted(pairs)
    assert "bone lf_tibia_tarsus-lf_claw" in found.records(frame=10)[0]["detail"]


def test_items_group_a_points_consecutive_frames_and_rank_by_score():
    from flylib.suspects import Suspects

    frame = np.array([3, 4, 5, 5, 9, 10, 12])
    point = np.array([1, 1, 1, 2, 1, 1, 1])
    score = np.array([1.0, 7.0, 1.0, 2.0, 1.5, 1.5, 3.0])
    reasons = [
        "jump",
        "jump;bone_length",
        "jump",
        "reprojection",
        "ransac_drop",
        "two_views;ransac_drop",
        "jump",
    ]
    s = Suspects(
        frame, point, score, reasons, [f"d{i}" for i in range(7)], np.zeros(13), ["a", "b", "c"]
    )
    items = s.items()
    assert [(it["point"], it["frames"]) for it in items] == [
        (1, [3, 4, 5]),
        (1, [12]),
        (2, [5]),
        (1, [9, 10]),
    ]
    first = items[0]
    assert first["peak_frame"] == 4 and first["score"] == 7.0 and first["detail"] == "d1"
    assert first["reasons"] == ["bone_length", "jump"] and first["point_name"] == "b"
    assert items[3]["reasons"] == ["ransac_drop", "two_views"]
    assert s.n_items == 4 and s.item.tolist() == [0, 0, 0, 2, 3, 3, 1]
    assert [r["item"] for r in s.records(frame=5)] == [0, 2]


def test_details_number_views_from_0_as_frames_and_points_with_the_camera_name():
    """Issue 36 (9): suspects.csv numbered views from 1 but frames and points from 0."""
    config, cameras, pts3d, pts2d, error = clean_case()
    bones = config.skeleton().bones
    views = config.view_names()
    names = list(config.skeleton().point_names)
    tarsus = names.index("lf_tibia_tarsus")
    seen = np.flatnonzero(np.isfinite(pts2d[:, 20, tarsus, 0]))
    err = error.copy()
    err[seen[0], 20, tarsus] = 40.0
    used = pts2d.copy()
    used[seen[1], 30, tarsus] = np.nan
    found = find_suspects(pts3d, used, err, bones, pts2d_input=pts2d, view_names=views)
    by_frame = {r["frame"]: r["detail"] for r in found.records()}
    assert by_frame[20].startswith(f"view {seen[0]} ({views[seen[0]]}) reprojects 40.0 px")
    assert by_frame[30] == f"view {seen[1]} ({views[seen[1]]}) dropped by the robust triangulation"
