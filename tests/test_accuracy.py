"""flylib.accuracy: the leave-one-camera-out (held-out-view) error against an OpenCV
reference, what it finds (a mis-calibrated camera, a worse method), the bone figures,
and the rule that decides where refinement's output keeps the triangulation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flylib.accuracy import (
    accuracy_summary,
    bone_length_spread,
    evaluation_windows,
    held_out_errors,
    keep_triangulation,
    left_right_asymmetry,
)
from flylib.config.params import TriangulationParams
from flylib.config.postprocessing import RefinementParams
from flylib.pipeline.triangulation import triangulation_method
from flylib.refinement.held_out import refinement_method
from flylib.skeleton import Skeleton, mirror_bones

from rough_rig import make_case
from synthetic import POINT_NAMES, project_opencv

DLT = TriangulationParams(method="dlt")


def _kmat(intr):
    return np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])


def _case(frames=20, **kw):
    """The front-blind tethered fly of ``rough_rig`` (real rig geometry: f ~16,000 px at
    ~116 units, one side per camera), exact 2D unless ``noise_px`` says otherwise."""
    kw.setdefault("noise_px", 0.0)
    kw.setdefault("outlier_frac", 0.0)
    return make_case(frames, hard=True, **kw)


def test_held_out_error_matches_an_opencv_two_view_reference():
    """A point seen by exactly three cameras, one of them 4 px off: holding out each
    camera, the rest triangulate (two views) and project it back; cv2.triangulatePoints
    and cv2.projectPoints give the same pixels independently of flylib (to 1e-3 px: the
    two DLTs weigh inconsistent rows differently)."""
    case = _case(frames=3)
    pts2d = project_opencv(case.rig, case.truth)
    pts2d = np.where(np.isfinite(case.pts2d), pts2d, np.nan)
    p = POINT_NAMES.index("rm_femur_tibia")
    seen = np.flatnonzero(np.isfinite(pts2d[:, 0, p]).all(-1))
    assert len(seen) == 3  # rh, rm, rf: the front camera is blind
    biased = seen[1]
    pts2d[biased, :, :, 0] += 4.0
    held = held_out_errors(case.rig, pts2d, triangulation_method(DLT, case.rig))
    # without the biased camera the other two are exact: the error is the bias itself
    np.testing.assert_allclose(held["triangulation"][biased, :, p], 4.0, atol=1e-6)
    for v in seen:
        a, b = [u for u in seen if u != v]
        mats = []
        for u in (a, b):
            rmat = cv2.Rodrigues(np.asarray(case.rig.rvecs[u], float))[0]
            mats.append(_kmat(case.rig.intrs[u]) @ np.hstack([rmat, case.rig.tvecs[u][:, None]]))
        for t in range(3):
            xh = cv2.triangulatePoints(
                mats[0], mats[1], pts2d[a, t, p][:, None], pts2d[b, t, p][:, None]
            )
            x = (xh[:3] / xh[3]).ravel()
            ref, _ = cv2.projectPoints(
                x[None], case.rig.rvecs[v], case.rig.tvecs[v], _kmat(case.rig.intrs[v]), None
            )
            expected = np.linalg.norm(ref.ravel() - pts2d[v, t, p])
            assert held["triangulation"][v, t, p] == pytest.approx(expected, abs=1e-3)
            assert expected > 1.0  # the bias shows in every camera held out
    assert held["frames"].tolist() == [0, 1, 2]


def _panned(rig, view: str, degrees: float):
    """``rig`` with camera ``view`` turned ``degrees`` about its own vertical axis."""
    from flylib.camera.rig import CameraGroup

    rvecs, tvecs = np.array(rig.rvecs, float), np.array(rig.tvecs, float)
    i = list(rig.names).index(view)
    pan = cv2.Rodrigues(np.deg2rad([0.0, degrees, 0.0]))[0]
    rvecs[i] = cv2.Rodrigues(pan @ cv2.Rodrigues(rvecs[i])[0])[0].ravel()
    tvecs[i] = pan @ tvecs[i]
    return CameraGroup.from_arrays(list(rig.names), rvecs, tvecs, rig.intrs, rig.dists)


def test_a_miscalibrated_camera_stands_out_without_any_truth():
    """Detector-like 2D (1 px noise, 5 % outliers) through a rig whose rm camera is
    turned 0.05 degrees (about 14 px at f = 16,000): held out, rm misses by that
    much, and with three cameras a side the whole right side stands out from the left
    (the other two right cameras are triangulated through rm's error)."""
    case = _case(frames=40, noise_px=1.0, outlier_frac=0.05)
    wrong = _panned(case.rig, "rm", 0.05)
    method = triangulation_method(TriangulationParams(method="ransac"), wrong)
    held = held_out_errors(wrong, case.pts2d, method)
    skeleton = Skeleton.fly()
    summary = accuracy_summary(
        held["triangulation"],
        None,
        view_names=list(wrong.names),
        point_names=list(skeleton.point_names),
    )
    per_view = {k: v["median"] for k, v in summary["per_view"].items() if v["median"] is not None}
    assert "f" not in per_view  # blind: nothing to hold out
    shift = case.rig.intrs[1][0] * np.deg2rad(0.05)
    assert per_view["rm"] == pytest.approx(shift, rel=0.15)
    assert min(per_view[v] for v in ("rh", "rm", "rf")) > 3 * max(
        per_view[v] for v in ("lh", "lm", "lf")
    )
    right = held_out_errors(case.rig, case.pts2d, method)["triangulation"]
    assert np.nanmedian(right) < 3.0  # the right rig: about the noise
    assert summary["held_out_px"]["n"] == np.isfinite(held["triangulation"]).sum()


def test_the_refinement_method_held_out_beats_the_dlt_on_a_noisy_tethered_fly():
    """The refinement stage's method (its table and the fly's bones and rigid thorax),
    judged by the same held-out views as the triangulation it starts from: on 1 px
    noise through the real-geometry rig it predicts the held-out cameras better
    (measured 1.56 against 1.87 px median) and fills points the DLT leaves open."""
    case = _case(frames=12, noise_px=1.0)
    held = held_out_errors(
        case.rig,
        case.pts2d,
        triangulation_method(DLT, case.rig),
        refine=refinement_method(RefinementParams(), case.rig, Skeleton.fly()),
    )
    tri, ref = held["triangulation"], held["refinement"]
    assert ref.shape == tri.shape and np.isfinite(ref).sum() >= np.isfinite(tri).sum()
    assert np.nanmedian(ref) < 0.95 * np.nanmedian(tri)


def test_bone_spread_and_left_right_asymmetry_of_a_known_skeleton():
    skeleton = Skeleton.fly()
    bones = np.asarray(skeleton.bones, int)
    mirror = mirror_bones(skeleton)
    case = _case(frames=30)
    truth = case.truth.copy()
    spread = bone_length_spread(truth, bones)
    leg = np.array(
        [POINT_NAMES[i][:2] in ("lf", "rf", "lm", "rm", "lh", "rh") for i in bones[:, 0]]
    )
    np.testing.assert_allclose(spread[leg], 0.0, atol=1e-9)  # legs of constant bone length
    assert np.allclose(left_right_asymmetry(truth, bones, mirror)[leg], 0.0, atol=1e-9)
    # one left femur 10 % longer: asymmetry |1.1 - 1| / 1.05 for it and its twin
    i, j = (POINT_NAMES.index(n) for n in ("lm_coxa_trochanter", "lm_femur_tibia"))
    b = int(np.flatnonzero((bones[:, 0] == i) & (bones[:, 1] == j))[0])
    longer = truth.copy()
    longer[:, j] = truth[:, i] + 1.1 * (truth[:, j] - truth[:, i])
    asym = left_right_asymmetry(longer, bones, mirror)
    assert asym[b] == pytest.approx(0.1 / 1.05, rel=1e-9)
    assert asym[mirror[b]] == pytest.approx(0.1 / 1.05, rel=1e-9)
    # a length that alternates by +-10 % over frames: IQR / median of 0.2
    wobbly = truth.copy()
    factor = np.where(np.arange(30) % 2, 1.1, 0.9)[:, None]
    wobbly[:, j] = truth[:, i] + factor * (truth[:, j] - truth[:, i])
    assert bone_length_spread(wobbly, bones)[b] == pytest.approx(0.2, rel=1e-9)


def test_evaluation_windows_bound_the_frames_and_cover_the_recording():
    assert evaluation_windows(15) == [(0, 15)]
    assert evaluation_windows(0) == []
    windows = evaluation_windows(100_000)
    assert sum(hi - lo for lo, hi in windows) == 500 and len(windows) == 2
    assert windows[0][0] == 0 and windows[-1][1] == 100_000
    assert all(hi - lo == 250 for lo, hi in windows)
    assert evaluation_windows(501) == [(0, 250), (251, 501)]
    assert len(evaluation_windows(100_000, max_frames=1000)) == 4


def test_keep_triangulation_point_by_point_and_everywhere():
    rng = np.random.default_rng(0)
    tri = rng.uniform(1, 3, (4, 50, 3))
    ref = tri.copy()
    ref[:, :, 0] *= 0.5  # better
    ref[:, :, 1] *= 1.5  # worse
    ref[0, :, 2] = np.nan  # only compared where both reconstructed
    keep, everywhere = keep_triangulation(tri, ref)
    assert keep.tolist() == [False, True, False] and not everywhere
    # a point better in median but with a worse tail keeps the triangulation too
    tail = tri.copy()
    tail[:, :5, 0] = 40.0
    keep, _ = keep_triangulation(tri, np.where(np.arange(3) == 0, tail, tri))
    assert keep[0]
    # worse everywhere: every point keeps the triangulation
    keep, everywhere = keep_triangulation(tri, tri * 1.2)
    assert keep.all() and everywhere
    # a point no held-out view can check (seen by two cameras at most: its triangulation
    # without one view is NaN) follows the points that can be checked (issue 46)
    tri[:, :, 2] = np.nan
    keep, everywhere = keep_triangulation(tri, tri * [0.5, 0.8, 1.0])
    assert keep.tolist() == [False, False, False] and not everywhere  # better where checked
    keep, everywhere = keep_triangulation(tri, tri * [0.5, 1.5, 1.0])
    assert keep.tolist() == [False, True, True] and not everywhere  # worse over the points checked
    # nothing comparable: every point keeps the triangulation
    keep, everywhere = keep_triangulation(tri, np.full_like(tri, np.nan))
    assert keep.all() and everywhere
