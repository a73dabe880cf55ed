"""Camera / CameraGroup: the orbit convention, config parsing, stacked views, projection."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flylib.camera import jax_model
from flylib.camera.rig import Camera, CameraGroup, orbit_extrinsics
from flylib.config import Config
from flylib.errors import ConfigError

from rig_constants import AZIMUTHS, DISTANCE, FOCAL, IMAGE_SIZE

SIZES = {name: IMAGE_SIZE for name in AZIMUTHS}


def rig_config(**defaults) -> Config:
    base = {
        "focal_length_px": [FOCAL, FOCAL],
        "distortion_coefficients": [],
        "look_at": [0.0, 0.0, 0.0],
        "distance": DISTANCE,
        "elevation_deg": 0.0,
        "roll_deg": 0.0,
        **defaults,
    }
    cams = {name: {"azimuth_deg": az} for name, az in AZIMUTHS.items()}
    return Config.from_dict({"cameras": {"defaults": base, **cams}})


def cameras_config(defaults: dict, cams: dict) -> Config:
    return Config.from_dict({"cameras": {"defaults": defaults, **cams}})


@pytest.fixture(scope="module")
def default_rig() -> CameraGroup:
    return CameraGroup.from_config(rig_config(), image_sizes=SIZES)


# -- the orbit convention ---------------------------------------------------------------


def test_default_rig_positions_and_look_at(default_rig):
    assert default_rig.names == list(AZIMUTHS)
    for cam in default_rig:
        az = np.deg2rad(AZIMUTHS[cam.name])
        np.testing.assert_allclose(
            cam.position, DISTANCE * np.array([np.cos(az), np.sin(az), 0.0]), atol=1e-12
        )
        np.testing.assert_allclose(cam.rmat @ cam.rmat.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(cam.rmat) == pytest.approx(1.0)
        # The origin (look_at) is on the optical axis, in front of the camera.
        np.testing.assert_allclose(cam.project(np.zeros(3)), [480.0, 240.0], atol=1e-9)
        assert (cam.rmat @ np.zeros(3) + cam.tvec)[2] == pytest.approx(DISTANCE)


def test_world_up_appears_above_the_centre_in_every_camera(default_rig):
    up = default_rig.project(np.array([0.0, 0.0, 1.0]))  # (V, 2)
    np.testing.assert_allclose(up[:, 0], 480.0, atol=1e-9)
    np.testing.assert_allclose(up[:, 1], 240.0 - FOCAL / DISTANCE, rtol=1e-12)


def test_azimuth_sides(default_rig):
    # Fly facing +x: its front appears on the image right in the right-side camera
    # (rm, azimuth -90) and on the left in the left-side camera (lm, +90); the front
    # camera (azimuth 0, on +x) sees the fly's left (+y) on its image right.
    front = np.array([1.0, 0.0, 0.0])
    left = np.array([0.0, 1.0, 0.0])
    assert default_rig["rm"].project(front)[0] > 480.0
    assert default_rig["lm"].project(front)[0] < 480.0
    assert default_rig["f"].project(left)[0] > 480.0
    np.testing.assert_allclose(default_rig["f"].position, [DISTANCE, 0, 0], atol=1e-12)


def test_elevation_and_roll():
    rvec, tvec = orbit_extrinsics(
        look_at=(1.0, 2.0, 3.0), distance=10.0, azimuth_deg=30.0, elevation_deg=40.0
    )
    cam = Camera(rvec, tvec, [100.0, 100.0, 50.0, 50.0], [], name="c")
    el, az = np.deg2rad(40.0), np.deg2rad(30.0)
    expected = np.array([1.0, 2.0, 3.0]) + 10.0 * np.array(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    )
    np.testing.assert_allclose(cam.position, expected, atol=1e-12)
    np.testing.assert_allclose(cam.project(np.array([1.0, 2.0, 3.0])), [50.0, 50.0], atol=1e-9)
    assert cam.project(np.array([1.0, 2.0, 4.0]))[1] < 50.0  # up is still up
    # Straight down (elevation 90) is well defined.
    rvec, tvec = orbit_extrinsics(distance=5.0, azimuth_deg=0.0, elevation_deg=90.0)
    assert np.all(np.isfinite(rvec)) and np.allclose(
        -jax_model.rvec_to_rmat_one(rvec).T @ tvec, [0, 0, 5]
    )
    # Roll +90: what was above the centre now appears to its right (clockwise).
    rvec, tvec = orbit_extrinsics(distance=10.0, azimuth_deg=0.0, roll_deg=90.0)
    rolled = Camera(rvec, tvec, [100.0, 100.0, 50.0, 50.0], [])
    np.testing.assert_allclose(rolled.project(np.array([0.0, 0.0, 1.0])), [60.0, 50.0], atol=1e-9)


# -- config parsing -------------------------------------------------------------------------


def test_focal_scalar_or_pair_and_principal_point():
    group = CameraGroup.from_config(
        cameras_config(
            {"distance": 10.0, "focal_length_px": 500.0},
            {
                "a": {"azimuth_deg": 0},
                "b": {
                    "azimuth_deg": 90,
                    "focal_length_px": [400.0, 410.0],
                    "principal_point_px": [1.0, 2.0],
                },
            },
        ),
        image_sizes={"a": (480, 960)},
    )
    np.testing.assert_array_equal(group["a"].intr, [500.0, 500.0, 480.0, 240.0])
    np.testing.assert_array_equal(group["b"].intr, [400.0, 410.0, 1.0, 2.0])


def test_missing_principal_point_is_a_clear_error():
    config = cameras_config({"distance": 10.0, "focal_length_px": 500.0}, {"a": {"azimuth_deg": 0}})
    with pytest.raises(ConfigError, match=r"cameras\.a\.principal_point_px"):
        CameraGroup.from_config(config)


def test_explicit_extrinsics_override_orbit_defaults():
    rvec, tvec = [0.1, -0.2, 0.3], [0.5, 0.0, 12.0]
    group = CameraGroup.from_config(
        cameras_config(
            {"distance": 10.0, "focal_length_px": 500.0, "principal_point_px": [50.0, 40.0]},
            {"x": {"rvec": rvec, "tvec": tvec, "distortion_coefficients": [0.01, 0.0, 0.001, 0.0]}},
        )
    )
    np.testing.assert_array_equal(group["x"].rvec, rvec)
    np.testing.assert_array_equal(group["x"].tvec, tvec)
    np.testing.assert_array_equal(group["x"].dist, [0.01, 0.0, 0.001, 0.0])


@pytest.mark.parametrize(
    "spec, message",
    [
        ({"rvec": [0, 0, 0], "tvec": [0, 0, 1], "azimuth_deg": 3}, "both"),
        ({"rvec": [0, 0, 0]}, "both rvec and tvec"),
        ({"azimuth_deg": 0, "distance": -1.0}, "distance must be positive"),
        ({"azimuth_deg": "east"}, "azimuth_deg must be a finite number"),
        ({"azimuth_deg": 0, "focal_length_px": [1.0, 2.0, 3.0]}, "focal_length_px"),
        ({"azimuth_deg": 0, "distortion_coefficients": [0.0] * 13}, "at most 12"),
        ({"azimuth_deg": 0, "azimuth": 4}, "unknown key"),
        ({"distance": 3.0}, "azimuth_deg is required"),
    ],
)
def test_bad_camera_specs(spec, message):
    config = cameras_config(
        {"distance": 10.0, "focal_length_px": 500.0, "principal_point_px": [1, 1]}, {"bad": spec}
    )
    with pytest.raises(ConfigError, match=message):
        CameraGroup.from_config(config)


def test_no_cameras_is_an_error():
    with pytest.raises(ConfigError, match="no cameras"):
        CameraGroup.from_config(cameras_config({"distance": 1.0}, {}))


# -- stacked views, subsets, arrays ----------------------------------------------------------


def test_from_arrays_stacked_views_and_padding():
    rng = np.random.default_rng(0)
    rvecs, tvecs = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    intrs = rng.uniform(100, 200, size=(3, 4))
    dists = rng.normal(size=(3, 5)) * 0.01
    group = CameraGroup.from_arrays(["a", "b", "c"], rvecs, tvecs, intrs, dists)
    for got, ref in (
        (group.rvecs, rvecs),
        (group.tvecs, tvecs),
        (group.intrs, intrs),
        (group.dists, dists),
    ):
        np.testing.assert_array_equal(got, ref)
    mixed = CameraGroup(
        [
            Camera(rvecs[0], tvecs[0], intrs[0], [0.1, 0.2], name="p"),
            Camera(rvecs[1], tvecs[1], intrs[1], [], name="q"),
        ]
    )
    np.testing.assert_array_equal(mixed.dists, [[0.1, 0.2], [0.0, 0.0]])
    assert len(group) == 3 and [c.name for c in group] == ["a", "b", "c"]
    assert group[1] is group["b"]
    sub = group.subset(["c", "a"])
    assert sub.names == ["c", "a"]
    np.testing.assert_array_equal(sub.rvecs, rvecs[[2, 0]])
    with pytest.raises(KeyError, match="no camera 'z'"):
        group.subset(["z"])
    for v, cam in enumerate(group):
        kmat = np.array([[intrs[v, 0], 0, intrs[v, 2]], [0, intrs[v, 1], intrs[v, 3]], [0, 0, 1]])
        np.testing.assert_allclose(
            group.pmats[v],
            kmat @ np.column_stack([cv2.Rodrigues(rvecs[v])[0], tvecs[v]]),
            rtol=1e-13,
        )
        np.testing.assert_allclose(
            cam.position, -cv2.Rodrigues(rvecs[v])[0].T @ tvecs[v], atol=1e-13
        )


def test_group_projection_matches_jax_and_opencv_with_distortion():
    rng = np.random.default_rng(1)
    rvecs = rng.normal(size=(3, 3)) * 0.3
    tvecs = np.array([[0.0, 0.0, 6.0]] * 3) + rng.normal(size=(3, 3)) * 0.1
    intrs = np.array([[800.0, 810.0, 320.0, 240.0]] * 3)
    dists = rng.normal(size=(3, 8)) * 0.02
    group = CameraGroup.from_arrays(["a", "b", "c"], rvecs, tvecs, intrs, dists)
    pts = rng.normal(size=(4, 5, 3))
    got = group.project(pts)
    assert got.shape == (3, 4, 5, 2)
    np.testing.assert_allclose(
        got, np.asarray(jax_model.project_full(pts, rvecs, tvecs, intrs, dists)), rtol=1e-12
    )
    ref = cv2.projectPoints(pts.reshape(-1, 3), rvecs[1], tvecs[1], group[1].kmat, dists[1])[0][
        :, 0
    ]
    np.testing.assert_allclose(got[1].reshape(-1, 2), ref, rtol=1e-9)
    np.testing.assert_allclose(group["b"].project(pts), got[1], rtol=1e-12)


def test_group_triangulate_handles_distortion_exactly():
    rng = np.random.default_rng(2)
    azimuths = [-60.0, 0.0, 60.0, 120.0]
    ext = [orbit_extrinsics(distance=8.0, azimuth_deg=a, elevation_deg=10.0) for a in azimuths]
    rvecs, tvecs = np.stack([e[0] for e in ext]), np.stack([e[1] for e in ext])
    intrs = np.array([[900.0, 900.0, 320.0, 240.0]] * 4)
    dists = np.array([[-0.1, 0.02, 0.001, -0.001, 0.0]] * 4)
    group = CameraGroup.from_arrays(list("abcd"), rvecs, tvecs, intrs, dists)
    pts = rng.uniform(-1, 1, size=(6, 3))
    np.testing.assert_allclose(group.triangulate(group.project(pts)), pts, atol=1e-10)
    with pytest.raises(ValueError, match="3 views on axis 0 but the rig has 4"):
        group.triangulate(group.project(pts)[:3])
    # rays through distorted pixels: the NumPy path against the JAX kernel (fixed point
    # + Newton), and back through the lens onto the pixel
    from flylib.camera import jax_model

    for cam, pixel in zip(group, group.project(pts[0])):
        origin, direction = cam.backproject_ray(pixel)
        ref_origin, ref_direction = jax_model.backproject_ray_one(
            pixel, cam.rvec, cam.tvec, cam.intr, cam.dist
        )
        np.testing.assert_allclose(origin, ref_origin, atol=1e-12)
        np.testing.assert_allclose(direction, ref_direction, rtol=1e-10)
        np.testing.assert_allclose(cam.project(origin + 3.0 * direction), pixel, atol=1e-8)


def test_backproject_ray_through_group():
    group = CameraGroup.from_config(rig_config(), image_sizes=SIZES)
    pixels = group.project(np.array([0.3, -0.2, 0.1]))
    origins, directions = group.backproject_ray(pixels)
    np.testing.assert_allclose(origins, group.positions, atol=1e-12)
    far = origins + 2.0 * directions
    for v, cam in enumerate(group):
        np.testing.assert_allclose(cam.project(far[v]), pixels[v], atol=1e-7)
