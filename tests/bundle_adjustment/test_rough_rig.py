"""Bundle adjustment from a realistic rough rig, and its building blocks.

The case (``tests/rough_rig.py``): tethered fly, DeepFly3D-like long-focal rig with five
zero distortion coefficients, plan visibility, 1 px noise, 5 % outliers within +-80 px,
a starting rig 4 deg / 4 % / 0.1 deg off.
"""

from __future__ import annotations

import numpy as np
import pytest

from flylib.bundle_adjustment import bundle_adjust, camera_table
from flylib.bundle_adjustment.lm import ReducedSystem, block_structure, solve_lm
from flylib.bundle_adjustment.reseed import radial_folds, reseed_gross_cameras
from flylib.config import Config
from flylib.errors import ConfigError
from flylib.pipeline.inputs import stage_params
from tests.bundle_adjustment.test_bundle_adjustment import small_problem

from rough_rig import (
    LEG_POINTS,
    PREVIOUS_DEFAULTS,
    fit_with_default_config,
    make_case,
    rough_start,
    similarity_error,
    true_rig,
)
from synthetic import project_opencv

# -- the reduced camera system ---------------------------------------------------------


@pytest.mark.parametrize("bone_group", [None, np.array([0, 1, 0])])
@pytest.mark.parametrize("global_point", [None, 1])
def test_schur_step_equals_the_dense_damped_solve(bone_group, global_point):
    problem, x = small_problem(fixed=["*.intr[2]"], shared=[["*.dist"]], bone_group=bone_group)
    shared = None if global_point is None else np.arange(problem.n_points) == global_point
    blocks = block_structure(problem, shared)
    jac, res = problem.jacobian(x), problem.residuals(x)
    system = ReducedSystem(jac, res, blocks)
    lam = 0.1
    dg, dl = system.step(lam)
    dx = np.zeros_like(x)
    dx[blocks.global_cols] = dg
    local = blocks.block_cols >= 0
    dx[blocks.block_cols[local]] = dl[local]
    normal = (jac.T @ jac).toarray()
    reference = np.linalg.solve(
        normal + lam * np.diag(np.maximum(np.diag(normal), 1e-12)), -jac.T @ res
    )
    np.testing.assert_allclose(dx, reference, rtol=0, atol=1e-9 * np.abs(reference).max())
    # bone-coupled points share a block, a global point is in no block
    if bone_group is not None and global_point is None:
        assert blocks.block_cols.shape[1] >= 6
    if global_point is not None:
        assert not np.isin(problem.n_cam + 3 * global_point, blocks.block_cols)


def test_lm_reaches_the_least_squares_minimum_like_scipy():
    from scipy.optimize import least_squares

    from flylib.bundle_adjustment.problem import project_rows

    problem, x = small_problem(fixed=["*.intr", "*.dist", "rh.rvec", "rh.tvec", "rm.tvec[2]"])
    rng = np.random.default_rng(0)
    table, pts = problem.unpack(x)
    problem.xy = project_rows(pts[problem.point], table[problem.view]) + rng.normal(
        0, 1.0, problem.xy.shape
    )  # a consistent scene with 1 px noise
    x0 = x + rng.normal(0, 1e-3, x.size)
    ours = solve_lm(problem, x0, block_structure(problem), max_nfev=200, ftol=1e-12)
    ref = least_squares(
        problem.residuals,
        x0,
        jac=lambda v: problem.jacobian(v).toarray(),
        method="lm",
        xtol=1e-14,
        ftol=1e-14,
    )
    assert ours.cost == pytest.approx(ref.cost, rel=1e-6)


# -- distortion, re-seeding ------------------------------------------------------------


def test_radial_fold_check():
    assert not radial_folds(np.zeros(5), 0.5)
    assert not radial_folds(np.array([-0.2, 0.05, 0, 0, 0]), 0.5)
    # k1 = -400 turns r (1 + k1 r^2) back at r = 0.029, inside a 16,000 px lens's image
    assert radial_folds(np.array([-400.0, 0, 0, 0, 0]), 0.04)
    assert not radial_folds(np.array([-400.0, 0, 0, 0, 0]), 0.02)


def test_zero_distortion_stays_zero_on_long_lenses_by_default():
    case = make_case(30, seed=3)
    legs = list(LEG_POINTS)
    flat = case.pts2d[:, ::3][:, :, legs].reshape(7, -1, 2)
    result, refined, _ = bundle_adjust(
        case.start, flat, fixed=["*.intr"], max_nfev=20, max_rounds=2
    )
    assert np.all(np.asarray(refined.dists) == 0.0)
    assert result.report["free"]["distortion_held_at_zero"] == 35
    assert result.report["free"]["per_camera"]["f"] == ["rvec", "tvec"]
    _, freed, _ = bundle_adjust(
        case.start, flat, fixed=["*.intr"], max_nfev=5, max_rounds=1, distortion="free"
    )
    assert np.any(np.asarray(freed.dists) != 0.0)
    with pytest.raises(ConfigError, match="distortion"):
        bundle_adjust(case.start, flat, distortion="maybe")


def test_a_camera_aimed_degrees_off_is_resected_by_pnp():
    rig = true_rig(seed=5)
    truth = make_case(40, seed=5).truth[:, list(LEG_POINTS)].reshape(-1, 3)
    pts2d = project_opencv(rig, truth)  # every view sees every point here
    table = camera_table(rig)
    bad = table.copy()
    bad[2] = camera_table(rough_start(rig, orbit_deg=0.0, dist_frac=0.0, aim_deg=3.0, seed=2))[2]

    def triangulate(tab, use):
        from flylib.bundle_adjustment.adjust import cameras_from_table, ransac_points

        return ransac_points(cameras_from_table(rig.names, tab), pts2d, use, 40.0)

    usable = np.isfinite(pts2d).all(-1)
    fixed_table, reseeded, med = reseed_gross_cameras(
        bad, list(rig.names), pts2d, usable, 100.0, triangulate
    )
    assert reseeded == [f"{rig.names[2]}: pnp"] and med[2] > 300
    np.testing.assert_allclose(fixed_table[2, :6], table[2, :6], atol=1e-4)


# -- the rough case ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rough():
    return make_case(300, seed=0)


@pytest.mark.slow
def test_rough_rig_recovers_the_fly(rough):
    """From the rough rig (200 of 300 frames), default config. The issue's target is
    0.06 median bones (stretch 0.03); measured 0.0113, the true rig's own triangulation
    floor (0.0112). Before issue 12 (scipy, no facts about the fly): 0.088."""
    from flylib.triangulation import reconstruct

    start_err = np.nanmedian(
        similarity_error(reconstruct(rough.start, rough.pts2d)[0], rough.truth) / rough.bone
    )
    result, _, _, err = fit_with_default_config(rough)
    assert np.nanmedian(err) <= 0.03
    assert result.final_median_px < 1.0
    assert min(result.report["kept_fraction"].values()) > 0.85  # the issue: 67 %
    assert not [w for w in result.warnings if "poorly determined" in w]
    free = result.report["free"]
    # 24 leg bones, left = right: 12 lengths; 15 thorax distances, mirror images alike: 9
    assert free["rigid_points"] == 6 and free["bone_lengths"] == 12 + 9
    assert result.report["rigid"]["used"] and result.report["rigid"]["spread_bones"] < 0.05
    old, _, _, err_old = fit_with_default_config(rough, **PREVIOUS_DEFAULTS)
    assert np.nanmedian(err_old) < 0.5 * start_err
    # legs only, nothing about the fly: one side's cameras and points scale about the
    # front camera (an exact null direction), and the report says so
    assert [w for w in old.warnings if "poorly determined" in w]


@pytest.mark.slow
def test_true_rig_start_stays_true(rough):
    # measured 0.0113 (the true rig's triangulation: 0.0112)
    _, _, pts3d, err = fit_with_default_config(rough, rough.rig)
    assert np.nanmedian(err) <= 0.015
    # and in place, unaligned: the result's frame is where the starting rig put the fly
    # (aligned on the camera anchors instead, the rig's small refinements moved it)
    raw = np.linalg.norm(pts3d - rough.truth, axis=-1) / rough.bone
    assert np.nanmedian(raw) <= 0.02


@pytest.mark.slow
def test_hard_variant_finishes_with_a_warning():
    case = make_case(60, hard=True, seed=0)
    with pytest.warns(RuntimeWarning, match="poorly determined"):
        result, _, _, _ = fit_with_default_config(case, max_frames=60, max_rounds=3)
    assert any("poorly determined" in w for w in result.report["warnings"])
    assert len(result.report["reseeded"]) == 6  # every camera that sees something re-aimed
    assert result.report["unobserved"] == ["f"]
    kept = [k for k in result.report["kept_fraction"].values() if k is not None]
    assert min(kept) > 0.8  # neither side thrown away


def test_rigid_points_are_used_only_when_the_body_is_still():
    from flylib.bundle_adjustment import bundle_adjust_sequence
    from flylib.skeleton import Skeleton

    case = make_case(40, seed=2)
    moving = case.truth + np.cumsum(
        np.random.default_rng(0).normal(0, 0.3 * case.bone, (40, 1, 3)), axis=0
    )
    for truth, still in ((case.truth, True), (moving, False)):
        pts2d = project_opencv(case.rig, truth)
        pts2d[:, :, [p for p in range(38) if p not in LEG_POINTS]] = np.nan
        result, _, _ = bundle_adjust_sequence(
            case.rig,
            pts2d,
            None,
            Skeleton.fly(),
            fixed=["*.intr"],
            max_frames=20,
            max_nfev=3,
            max_rounds=1,
        )
        assert result.report["rigid"]["used"] is still
        assert result.report["free"]["rigid_points"] == (6 if still else 0)


def test_thorax_distances_pair_mirror_images():
    from flylib.bundle_adjustment.sequence import THORAX_POINTS, length_unknowns
    from flylib.skeleton import Skeleton

    skeleton = Skeleton.fly()
    names = list(skeleton.point_names)
    used = np.array(sorted(names.index(p) for p in THORAX_POINTS))
    bi, bj, _, group = length_unknowns(skeleton, used, 2, True, THORAX_POINTS)
    assert bi.size == 2 * 15  # every pair of the six, in each of two frames
    pair = {
        frozenset((names[used[i % 6]], names[used[j % 6]])): g for i, j, g in zip(bi, bj, group)
    }
    key = lambda a, b: pair[frozenset((f"{a}_thorax_coxa", f"{b}_thorax_coxa"))]  # noqa: E731
    assert key("lf", "rm") == key("rf", "lm") != key("lf", "lm") == key("rf", "rm")
    assert key("lf", "rf") != key("lm", "rm")
    assert len(set(group)) == 9
    _, _, _, group = length_unknowns(skeleton, used, 1, False, THORAX_POINTS)
    assert len(set(group)) == 15


def test_open_gauge_directions_count_what_held_entries_leave():
    from flylib.bundle_adjustment.gauge import gauge_refs, open_gauge_directions
    from flylib.bundle_adjustment.params import build_layout

    rig = true_rig()
    table, names = camera_table(rig), list(rig.names)
    assert open_gauge_directions(table, build_layout(names, 5, ["*.intr"])) == 7
    assert open_gauge_directions(table, build_layout(names, 5, ["f.rvec", "rm.tvec[2]"])) == 3
    assert open_gauge_directions(table, build_layout(names, 5, gauge_refs(table, names))) == 0
    # a camera that sees nothing does not pin the others
    seen = np.arange(7) != 3
    assert open_gauge_directions(table, build_layout(names, 5, ["f.rvec", "f.tvec"]), seen) == 7


def test_new_keys_are_validated_and_reach_stage_params():
    base = Config.default().data
    config = Config.from_dict(
        {
            **base,
            "bundle_adjustment": {
                **base["bundle_adjustment"],
                "solver": "lm",
                "symmetric_bones": True,
            },
        }
    )
    params = stage_params(config, "bundle_adjustment")["bundle_adjustment"]
    assert params["solver"] == "lm" and params["symmetric_bones"] is True
    assert "rigid_points" in params and "distortion" in params
    with pytest.raises(ConfigError, match="bundle_adjustment.solver"):
        Config.from_dict({**base, "bundle_adjustment": {"solver": "newton"}})
