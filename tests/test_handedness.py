"""flylib.handedness: a fly or its mirror image, from the skeleton's labelled legs; the
mirrored rig that keeps every pixel; the messages that name the cause and the switch."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flylib.camera.rig import CameraGroup
from flylib.config import Config
from flylib.demo import synthetic_fly
from flylib.handedness import (
    MIRROR_SWITCH,
    WORLD_MIRROR,
    Handedness,
    handedness,
    mirror_cameras,
    mirrored_refusal,
    rig_check,
    rig_handedness,
)
from flylib.pipeline.planning import config_rig
from flylib.skeleton import Skeleton

SKELETON = Skeleton.fly()


def _fly(frames: int = 40, seed: int = 0) -> np.ndarray:
    return synthetic_fly(frames, seed)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_fly_is_right_handed_and_its_mirror_image_is_mirrored_in_any_pose(seed):
    rng = np.random.default_rng(seed)
    turn = Rotation.random(random_state=seed).as_matrix()
    fly = _fly(seed=seed) @ turn.T + rng.normal(size=3) * 10
    plane = rng.normal(size=3)
    plane /= np.linalg.norm(plane)
    reflection = np.eye(3) - 2 * np.outer(plane, plane)  # any mirror, not only an axis
    right = handedness(fly, SKELETON)
    mirror = handedness(fly @ reflection.T, SKELETON)
    assert right.verdict == "right-handed" and right.score > 0.9 and not right.mirrored
    assert mirror.verdict == "mirrored" and mirror.score < -0.9 and mirror.mirrored
    assert mirror.score == pytest.approx(-right.score)
    assert right.frames == mirror.frames == 40
    assert "left legs are on the fly's right" in mirror.reason


def test_relabelling_left_as_right_is_a_mirror_image():
    """The labels decide, not the geometry: swapping every l*/r* label mirrors the fly."""
    fly = _fly()
    swap = [SKELETON.index(("r" if n[0] == "l" else "l") + n[1:]) for n in SKELETON.point_names]
    assert handedness(fly[:, swap], SKELETON).verdict == "mirrored"


def test_missing_points_and_a_minority_of_bad_frames_do_not_decide_it():
    rng = np.random.default_rng(3)
    fly = _fly(frames=60).copy()
    fly[rng.random(fly.shape[:2]) < 0.3] = np.nan  # 30 % of the points missing
    fly[:5] = fly[:5] * [1, 1, -1]  # 5 frames mirrored (e.g. a mislabelled burst)
    fly[5:10] = np.nan  # 5 frames with nothing
    found = handedness(fly, SKELETON)
    assert found.verdict == "right-handed" and found.score > 0.8
    assert found.frames <= 55


def test_no_measurable_frame_or_no_labelled_legs_is_undetermined_with_the_reason():
    empty = handedness(np.full((4, 38, 3), np.nan), SKELETON)
    assert empty.verdict == "undetermined" and np.isnan(empty.score) and empty.frames == 0
    assert empty.reason.startswith("0 of 4 frames have 3D for a front and a hind body-coxa")
    bare = Skeleton(point_names=("a", "b", "c"), limbs={"x": ("a", "b")})
    unsided = handedness(np.zeros((2, 3, 3)), bare)
    assert unsided.verdict == "undetermined" and "no legs labelled" in unsided.reason
    flat = _fly()
    flat[..., 2] = 0.0  # a flattened fly: no dorsal direction
    assert handedness(flat, SKELETON).verdict == "undetermined"
    assert Handedness(float("nan"), "undetermined", "x", 0).as_dict()["score"] is None


def test_fewer_than_ten_measured_frames_are_undetermined_whatever_they_show():
    """Issue 45: 9 mirror-image frames among 60 with a hind body-coxa point missing elsewhere
    are too few; a 10th makes the verdict."""
    whole = _fly(frames=60) @ WORLD_MIRROR
    hind = [SKELETON.index(f"{side}h_thorax_coxa") for side in "lr"]
    fly = whole.copy()
    fly[9:, hind] = np.nan
    few = handedness(fly, SKELETON)
    assert few.verdict == "undetermined" and few.frames == 9 and few.score < -0.9
    assert few.reason.endswith(
        "median of 9 frames: too few to tell (9 of 60 frames have 3D for a front and a hind "
        "body-coxa point, a left and a right leg point and a leg tip; a verdict needs 10)"
    )
    fly[9, hind] = whole[9, hind]
    assert handedness(fly, SKELETON).verdict == "mirrored"


def _rig(distorted: bool = True) -> CameraGroup:
    config = Config.default()
    rig = config_rig(config, image_sizes={v: (480, 960) for v in config.view_names()})
    dists = np.zeros((len(rig.names), 5))
    if distorted:  # every coefficient, tangential ones included
        dists[:] = [0.3, -2.0, 0.004, -0.006, 5.0]
    return CameraGroup.from_arrays(rig.names, rig.rvecs, rig.tvecs, rig.intrs, dists)


def test_the_mirrored_rig_sees_the_mirror_world_in_the_same_pixels():
    rig = _rig()
    fly = _fly(frames=10)
    mirrored = mirror_cameras(rig)
    np.testing.assert_allclose(
        mirrored.project(fly @ WORLD_MIRROR), rig.project(fly), atol=1e-8, rtol=0
    )
    np.testing.assert_array_equal(mirrored.intrs, rig.intrs)
    np.testing.assert_array_equal(mirrored.dists, rig.dists)
    assert all(np.linalg.det(r) == pytest.approx(1.0) for r in mirrored.rmats)
    # the same 2D triangulates to the mirror image: a fly becomes mirrored and back
    pixels = rig.project(fly)
    np.testing.assert_allclose(mirrored.triangulate(pixels), fly @ WORLD_MIRROR, atol=1e-6)
    assert handedness(mirrored.triangulate(pixels), SKELETON).verdict == "mirrored"
    twice = mirror_cameras(mirrored)
    np.testing.assert_allclose(twice.project(fly), rig.project(fly), atol=1e-8, rtol=0)


def test_an_orbit_rig_with_its_sides_swapped_reconstructs_a_mirror_image():
    """A starting rig mirrored by its cameras table (azimuths negated: the left cameras
    where the right ones are) gives the same fly mirrored, from the same 2D."""
    config = Config.default()
    sizes = {v: (480, 960) for v in config.view_names()}
    rig = config_rig(config, image_sizes=sizes)
    table = dict(config.data["cameras"])
    swapped = {
        name: {**spec, "azimuth_deg": -spec["azimuth_deg"]} if name != "defaults" else spec
        for name, spec in table.items()
    }
    mirrored = config_rig(Config.from_dict({**config.data, "cameras": swapped}), image_sizes=sizes)
    fly = _fly(frames=10)
    pixels = rig.project(fly)
    assert handedness(rig.triangulate(pixels), SKELETON).verdict == "right-handed"
    assert handedness(mirrored.triangulate(pixels), SKELETON).verdict == "mirrored"


def _table_rig(specs: dict | None = None, defaults: dict | None = None) -> CameraGroup:
    """The rig a cameras table types (the default config's, or ``specs`` over its defaults)."""
    base_defaults, base = Config.default().camera_table()
    specs = base if specs is None else specs
    sizes = dict.fromkeys(specs, (480, 960))
    return CameraGroup.from_table(specs, base_defaults if defaults is None else defaults, sizes)


def _moved(rig: CameraGroup, rotation: np.ndarray, scale: float, shift: np.ndarray) -> CameraGroup:
    """The same cameras in the world ``X' = scale * rotation @ X + shift`` (same pixels)."""
    rmats = np.asarray(rig.rmats) @ rotation.T
    tvecs = scale * np.asarray(rig.tvecs) - rmats @ shift
    rvecs = Rotation.from_matrix(rmats).as_rotvec()
    return CameraGroup.from_arrays(rig.names, rvecs, tvecs, rig.intrs, rig.dists)


def test_a_calibrations_handedness_from_its_cameras_against_the_cameras_table():
    """Issue 46: decided from geometry alone (camera centres and image-up directions),
    whatever the calibration's world axes, origin and unit."""
    typed = _table_rig()
    assert rig_handedness(typed, typed).verdict == "right-handed"
    assert rig_handedness(typed, typed).score == pytest.approx(1.0)
    turned = Rotation.from_euler("zyx", [40, -70, 15], degrees=True).as_matrix()
    moved = _moved(typed, turned, 0.01, np.array([3.0, -2.0, 50.0]))  # mm to m, elsewhere
    assert rig_handedness(moved, typed).verdict == "right-handed"
    fly = _fly(frames=3)
    np.testing.assert_allclose(  # the same cameras: the same pixels of the moved fly
        moved.project(0.01 * fly @ turned.T + [3.0, -2.0, 50.0]), typed.project(fly), atol=1e-6
    )
    # one world axis flipped: y (the left cameras where the right ones are), or z (the
    # switch calibration.mirror applies, which mirrors it back)
    _, table = Config.default().camera_table()
    swapped = {name: {"azimuth_deg": -spec["azimuth_deg"]} for name, spec in table.items()}
    for mirrored in (_table_rig(swapped), mirror_cameras(typed), mirror_cameras(moved)):
        verdict = rig_handedness(mirrored, typed)
        assert verdict.verdict == "mirrored" and verdict.score == pytest.approx(-1.0), verdict
        assert "fit the cameras table's only mirrored (residual 0.00" in verdict.reason
    assert rig_handedness(mirror_cameras(mirror_cameras(typed)), typed).verdict == "right-handed"


def test_a_calibration_that_does_not_match_the_cameras_table_is_undetermined():
    typed = _table_rig()
    two = rig_handedness(typed, _table_rig({"f": {"azimuth_deg": 0}, "lf": {"azimuth_deg": 45}}))
    assert two.verdict == "undetermined" and two.reason == "2 cameras shared; needs 3"
    # three cameras in a row, looking the same way: its mirror image fits as well
    line = _table_rig({f"c{i}": {"azimuth_deg": 0, "distance": 100.0 + 50 * i} for i in range(3)})
    verdict = rig_handedness(line, line)
    assert verdict.verdict == "undetermined" and verdict.score == 0.0, verdict
    assert verdict.reason.endswith(": the other handedness fits about as well")
    # every camera in one place: no centres to fit
    ahead = np.tile([0.0, 0.0, 100.0], (3, 1))
    same = CameraGroup.from_arrays("abc", 0 * ahead, ahead, typed.intrs[:3], typed.dists[:3])
    assert rig_handedness(same, same).verdict == "undetermined"
    # one camera upside down (its image up against the table's)
    _, table = Config.default().camera_table()
    rolled = _table_rig({**table, "lf": {"azimuth_deg": 45, "roll_deg": 180}})
    verdict = rig_handedness(rolled, typed)
    assert verdict.verdict == "undetermined" and "too poor a fit" in verdict.reason, verdict
    # the cameras in another order than the table's: no rigid fit either way
    shuffled = _table_rig()
    shuffled = CameraGroup.from_arrays(
        typed.names,
        *(
            np.asarray(a)[[3, 0, 6, 1, 5, 2, 4]]
            for a in (shuffled.rvecs, shuffled.tvecs, shuffled.intrs, shuffled.dists)
        ),
    )
    verdict = rig_handedness(shuffled, typed)
    assert verdict.verdict == "undetermined" and "too poor a fit" in verdict.reason, verdict


@pytest.mark.shared
@pytest.mark.parametrize("name", ["calib.pkl", "df3d_result.pkl"])
def test_the_package_examples_calibration_is_a_mirror_image_as_its_own_3d(
    df3d_package_example_dir, name
):
    """DeepFly3D's package example: its calibration (alone, and inside its result) is the
    mirror image of flylib's default rig, as the fly DeepFly3D triangulated with it is."""
    import pickle

    from flylib.interop.anipose import load_calibration
    from flylib.interop.df3d import df3d_joint_to_fly38

    typed = _table_rig()
    spec = {"file": str(df3d_package_example_dir / name), "format": "deepfly3d"}
    rig = load_calibration(spec, typed.names)
    verdict = rig_handedness(rig, typed)
    assert verdict.verdict == "mirrored" and verdict.score < -0.95, verdict
    assert rig_handedness(mirror_cameras(rig), typed).verdict == "right-handed"
    with (df3d_package_example_dir / "df3d_result.pkl").open("rb") as fh:
        points3d = pickle.load(fh)["points3d"]  # the test's own trusted copy
    fly = np.full((len(points3d), SKELETON.n_points, 3), np.nan)
    for j in range(points3d.shape[1]):
        fly[:, SKELETON.index(df3d_joint_to_fly38(j))] = points3d[:, j]
    assert handedness(fly, SKELETON).verdict == "mirrored"


RIGHT = Handedness(0.95, "right-handed", "fine", 15)
MIRROR = Handedness(-0.96, "mirrored", "left legs on the right", 15)


def test_a_mirrored_calibration_file_is_named_with_the_one_switch():
    entry = rig_check(MIRROR, rig="the calibration file /d/calib.pkl", from_file=True)
    assert entry["verdict"] == "mirrored" and entry["cause"] == "calibration"
    assert entry["score"] == -0.96 and entry["starting_rig"] is None
    message = entry["message"]
    assert message.startswith("the 3D is the fly's mirror image, its left legs on its right")
    assert "the calibration file /d/calib.pkl gives a mirror-image world" in message
    assert MIRROR_SWITCH in message and "docs/how-it-works/handedness.md" in message
    assert rig_check(RIGHT, rig="x", from_file=True)["message"] is None


def test_bundle_adjustment_is_blamed_on_its_starting_rig_or_on_itself():
    kept = rig_check(
        MIRROR, rig="the calibration file c.pkl", from_file=True, adjusted=True, start=MIRROR
    )
    assert kept["cause"] == "calibration" and "bundle adjustment started from it" in kept["message"]
    assert kept["starting_rig"]["verdict"] == "mirrored"
    flipped = rig_check(
        MIRROR, rig="the config's cameras table", from_file=False, adjusted=True, start=RIGHT
    )
    assert flipped["cause"] == "bundle_adjustment"
    assert "turned its starting rig (the config's cameras table" in flipped["message"]
    assert "depth-reversed twin" in flipped["message"]
    table = rig_check(
        MIRROR, rig="the config's cameras table", from_file=False, adjusted=True, start=MIRROR
    )
    assert table["cause"] == "starting_rig" and MIRROR_SWITCH not in table["message"]
    assert "which side of the fly each camera films" in table["message"]
    undone = rig_check(MIRROR, rig="the calibration file c.pkl", from_file=True, mirror_set=True)
    assert "set calibration: {mirror: false}" in undone["message"]


class _Result:
    def __init__(self, pts3d, meta):
        self.pts3d, self.meta, self.skeleton = pts3d, meta, SKELETON


def test_the_refusal_repeats_the_stored_cause_or_judges_an_older_file_itself():
    stored = rig_check(MIRROR, rig="the calibration file c.pkl", from_file=True)
    line = mirrored_refusal(_Result(None, {"handedness": stored}), "r/results.h5", "kinematics")
    assert line.startswith("r/results.h5: kinematics refused: the 3D is the fly's mirror image")
    assert "c.pkl" in line and MIRROR_SWITCH in line
    assert line.endswith("set kinematics: {allow_mirrored: true}")
    fine = rig_check(RIGHT, rig="x", from_file=False)
    assert mirrored_refusal(_Result(None, {"handedness": fine}), "r", "kinematics") is None
    older = _Result(_fly() @ WORLD_MIRROR, {})  # assembled before the check existed
    line = mirrored_refusal(older, "old.h5", "neuromechfly")
    assert "mirror image" in line and "neuromechfly: {allow_mirrored: true}" in line
    assert mirrored_refusal(_Result(_fly(), {}), "old.h5", "neuromechfly") is None


def test_the_switches_leave_existing_params_hashes_alone_at_their_defaults():
    """``calibration.mirror: false`` and ``allow_mirrored: false`` track as absent; set,
    they re-run the stages they change."""
    from flylib.pipeline.inputs import stage_params

    base = Config.default().data
    with_file = {**base, "calibration": {"file": "calib.pkl"}}
    off = Config.from_dict({**base, "calibration": {"file": "calib.pkl", "mirror": False}})
    on = Config.from_dict({**base, "calibration": {"file": "calib.pkl", "mirror": True}})
    assert stage_params(off, "assemble") == stage_params(Config.from_dict(with_file), "assemble")
    assert stage_params(on, "assemble") != stage_params(off, "assemble")
    for stage in ("kinematics", "neuromechfly"):
        default = stage_params(Config.default(), stage)
        explicit = Config.from_dict({**base, stage: {**base[stage], "allow_mirrored": False}})
        allowed = Config.from_dict({**base, stage: {**base[stage], "allow_mirrored": True}})
        assert stage_params(explicit, stage) == default
        assert "allow_mirrored" not in str(default)
        assert stage_params(allowed, stage) != default
        assert getattr(allowed, stage).allow_mirrored is True
