"""Cameras and camera rigs: building them from the config and using them.

Orbit convention (``look_at``, ``distance``, ``azimuth_deg``, ``elevation_deg``, ``roll_deg``),
world up = +z:

* the camera centre is ``look_at + distance * (cos e cos a, cos e sin a, sin e)``: azimuth 0
  puts the camera on the +x axis, azimuth +90 on +y (counter-clockwise seen from above),
  positive elevation above the ``look_at`` plane;
* the optical axis (camera +z) points from the centre at ``look_at``;
* image x (camera +x) is the horizontal ``(-sin a, cos a, 0)``; image y (camera +y, pointing
  down in the image) is ``z_cam x x_cam``, so world +z appears above the image centre at every
  azimuth and any elevation below 90 degrees;
* ``roll_deg`` then rotates the camera frame about its optical axis (``R = Rz(roll) @
  R_orbit``): the scene appears turned clockwise on screen.

With the fly facing +x, +y is its left: the default rig's right-side cameras (rh, rm, rf) sit
at negative azimuths, the front camera at azimuth 0."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ..errors import ConfigError, did_you_mean
from . import model as camera_model

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

log = logging.getLogger(__name__)

ORBIT_KEYS = ("look_at", "distance", "azimuth_deg", "elevation_deg", "roll_deg")
EXPLICIT_KEYS = ("rvec", "tvec")
INTRINSIC_KEYS = ("focal_length_px", "principal_point_px", "distortion_coefficients")
CAMERA_KEYS = frozenset(ORBIT_KEYS + EXPLICIT_KEYS + INTRINSIC_KEYS)


def _vector(spec: Mapping, key: str, size: int | None, where: str) -> np.ndarray:
    try:
        arr = np.asarray(spec[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}.{key} must be a list of numbers, got {spec[key]!r}") from None
    if arr.ndim != 1 or (size is not None and arr.size != size) or not np.all(np.isfinite(arr)):
        want = f"{size} finite numbers" if size is not None else "a flat list of finite numbers"
        raise ConfigError(f"{where}.{key} must be {want}, got {spec[key]!r}")
    return arr


def _number(spec: Mapping, key: str, default: float | None, where: str) -> float:
    if key not in spec:
        if default is None:
            raise ConfigError(f"{where}.{key} is required for the orbit parameterization")
        return default
    value = spec[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ConfigError(f"{where}.{key} must be a finite number, got {value!r}")
    return float(value)


def orbit_extrinsics(
    look_at: Float[np.ndarray, " 3"] | tuple[float, float, float] = (0.0, 0.0, 0.0),
    distance: float = 1.0,
    azimuth_deg: float = 0.0,
    elevation_deg: float = 0.0,
    roll_deg: float = 0.0,
) -> tuple[Float[np.ndarray, " 3"], Float[np.ndarray, " 3"]]:
    """World-to-camera ``(rvec, tvec)`` of a camera ``distance`` (> 0) from ``look_at``, the
    world point on its optical axis (the orbit convention of the module docstring)."""
    az, el, roll = np.deg2rad([azimuth_deg, elevation_deg, roll_deg])
    outward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    centre = np.asarray(look_at, dtype=np.float64) + distance * outward
    z_cam = -outward
    x_cam = np.array([-np.sin(az), np.cos(az), 0.0])
    y_cam = np.cross(z_cam, x_cam)
    c, s = np.cos(roll), np.sin(roll)
    roll_mat = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    rmat = roll_mat @ np.stack([x_cam, y_cam, z_cam])
    # NumPy, not JAX: at config time, op-by-op dispatch would compile dozens of tiny kernels.
    rvec = camera_model.rmat_to_rvec_numpy(rmat)
    return rvec, -rmat @ centre


def resolve_extrinsics(
    spec: Mapping, where: str = "cameras"
) -> tuple[Float[np.ndarray, " 3"], Float[np.ndarray, " 3"]]:
    """``(rvec, tvec)`` from a camera spec (defaults merged in): ``rvec``/``tvec`` or orbit keys;
    a lone ``rvec`` or bad orbit keys are a ConfigError naming ``where`` (``"cameras.rh"``)."""
    has_r, has_t = "rvec" in spec, "tvec" in spec
    if has_r != has_t:
        raise ConfigError(f"{where}: give both rvec and tvec, or neither (use the orbit keys)")
    if has_r:
        return _vector(spec, "rvec", 3, where), _vector(spec, "tvec", 3, where)
    look_at = _vector(spec, "look_at", 3, where) if "look_at" in spec else np.zeros(3)
    distance = _number(spec, "distance", None, where)
    if distance <= 0:
        raise ConfigError(f"{where}.distance must be positive, got {distance}")
    return orbit_extrinsics(
        look_at=look_at,
        distance=distance,
        azimuth_deg=_number(spec, "azimuth_deg", None, where),
        elevation_deg=_number(spec, "elevation_deg", 0.0, where),
        roll_deg=_number(spec, "roll_deg", 0.0, where),
    )


def resolve_intrinsics(
    spec: Mapping, image_size: tuple[int, int] | None = None, where: str = "cameras"
) -> tuple[Float[np.ndarray, " 4"], Float[np.ndarray, " K"]]:
    """``(intr, dist)`` from a camera spec: ``focal_length_px`` is a number or ``[fx, fy]``;
    ``principal_point_px`` is ``[cx, cy]``, or, when absent, the centre ``(w / 2, h / 2)`` of
    ``image_size`` ``(h, w)``; ``distortion_coefficients`` is an OpenCV-ordered list (<= 12). A
    missing or malformed key, or no principal point, is a ConfigError."""
    if "focal_length_px" not in spec:
        raise ConfigError(f"{where}.focal_length_px is required (a number or [fx, fy])")
    focal = np.atleast_1d(np.asarray(spec["focal_length_px"], dtype=object))
    try:
        focal = focal.astype(np.float64)
    except (TypeError, ValueError):
        focal = np.array([np.nan])
    if focal.ndim != 1 or focal.size not in (1, 2) or not np.all(np.isfinite(focal) & (focal > 0)):
        raise ConfigError(
            f"{where}.focal_length_px must be a positive number or [fx, fy], "
            f"got {spec['focal_length_px']!r}"
        )
    fx, fy = (focal[0], focal[0]) if focal.size == 1 else focal
    if "principal_point_px" in spec:
        cx, cy = _vector(spec, "principal_point_px", 2, where)
    elif image_size is not None:
        height, width = image_size
        cx, cy = width / 2.0, height / 2.0
    else:
        raise ConfigError(
            f"{where}.principal_point_px is not set and the image size is unknown: "
            "set principal_point_px = [cx, cy] or pass image_sizes"
        )
    dist = (
        _vector(spec, "distortion_coefficients", None, where)
        if spec.get("distortion_coefficients") not in (None, [])
        else np.zeros(0)
    )
    if dist.size > camera_model.N_DIST_COEFFS:
        raise ConfigError(
            f"{where}.distortion_coefficients has {dist.size} values; at most "
            f"{camera_model.N_DIST_COEFFS} (OpenCV k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4)"
        )
    return np.array([fx, fy, cx, cy], dtype=np.float64), dist


@dataclass(eq=False)
class Camera:
    """One pinhole camera with OpenCV distortion: world-to-camera ``rvec`` (axis-angle) and
    ``tvec``, ``(3,)`` each; ``intr`` ``[fx, fy, cx, cy]`` in raw-footage pixels; ``dist``
    ``(K,)``, ``K <= 12`` (may be empty); ``name``, the view's name or ``None``."""

    rvec: Float[np.ndarray, " 3"]
    tvec: Float[np.ndarray, " 3"]
    intr: Float[np.ndarray, " 4"]
    dist: Float[np.ndarray, " K"]
    name: str | None = None

    def __post_init__(self) -> None:
        self.rvec = np.asarray(self.rvec, dtype=np.float64).reshape(3)
        self.tvec = np.asarray(self.tvec, dtype=np.float64).reshape(3)
        intr = np.asarray(self.intr, dtype=np.float64).reshape(-1)
        if intr.size == 3:  # [f, cx, cy]
            intr = np.array([intr[0], intr[0], intr[1], intr[2]])
        if intr.size != 4:
            raise ValueError(f"camera {self.name!r}: intr must be [fx, fy, cx, cy], got {intr}")
        self.intr = intr
        self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if self.dist.size > camera_model.N_DIST_COEFFS:
            raise ValueError(
                f"camera {self.name!r}: at most {camera_model.N_DIST_COEFFS} distortion "
                f"coefficients, got {self.dist.size}"
            )

    @classmethod
    def from_spec(
        cls, spec: Mapping, name: str | None = None, image_size: tuple[int, int] | None = None
    ) -> Camera:
        """Build a camera from a config spec (defaults merged in), ConfigError on a bad key;
        ``image_size`` ``(height, width)`` centres the principal point if the spec has none."""
        where = f"cameras.{name}" if name else "cameras"
        unknown = sorted(set(spec) - CAMERA_KEYS)
        if unknown:
            raise ConfigError(
                f"{where}: unknown key(s) {unknown}; {did_you_mean(unknown[0], CAMERA_KEYS)}allowed: {sorted(CAMERA_KEYS)}"
            )
        rvec, tvec = resolve_extrinsics(spec, where)
        intr, dist = resolve_intrinsics(spec, image_size, where)
        return cls(rvec=rvec, tvec=tvec, intr=intr, dist=dist, name=name)

    @property
    def rmat(self) -> Float[np.ndarray, "3 3"]:
        """World-to-camera rotation matrix ``(3, 3)``."""
        return camera_model.rvec_to_rmat_numpy(self.rvec)

    @property
    def kmat(self) -> Float[np.ndarray, "3 3"]:
        """Camera matrix ``K`` ``(3, 3)``."""
        return camera_model.intr_to_kmat_numpy(self.intr)

    @property
    def pmat(self) -> Float[np.ndarray, "3 4"]:
        """Projection matrix ``K [R | t]`` ``(3, 4)`` (ignores distortion)."""
        return self.kmat @ np.concatenate([self.rmat, self.tvec[:, None]], axis=1)

    @property
    def position(self) -> Float[np.ndarray, " 3"]:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.rmat.T @ self.tvec

    def project(self, pts3d: Float[np.ndarray, "*pts 3"]) -> Float[np.ndarray, "*pts 2"]:
        """Project world points ``(*pts, 3)`` to pixels ``(*pts, 2)``."""
        return camera_model.project_numpy(
            pts3d,
            self.rmat[None],
            self.tvec[None],
            self.intr[None],
            self.dist[None],
        )[0]

    def backproject_ray(
        self, pixel: Float[np.ndarray, " 2"]
    ) -> tuple[Float[np.ndarray, " 3"], Float[np.ndarray, " 3"]]:
        """World ray ``(origin, direction)`` of a pixel ``(2,)`` (NumPy ``backproject_ray_one``)."""
        fx, fy, cx, cy = self.intr
        norm = (np.asarray(pixel, dtype=np.float64) - [cx, cy]) / [fx, fy]
        x, y = camera_model.undistort_normalized(norm, self.dist)
        return camera_model.ray_from_normalized(np, x, y, self.rmat, self.tvec)


class HasCameraTable(Protocol):
    """What :meth:`CameraGroup.from_config` reads: :meth:`flylib.config.Config.camera_table`."""

    def camera_table(self) -> tuple[dict, dict]: ...


class CameraGroup:
    """The rig: named cameras in view order (the V axis of every array)."""

    def __init__(self, cameras: Mapping[str, Camera] | Iterable[Camera]):
        if isinstance(cameras, Mapping):
            items = dict(cameras)
        else:
            items = {}
            for cam in cameras:
                if cam.name is None:
                    raise ValueError("CameraGroup needs named cameras (Camera.name is None)")
                items[cam.name] = cam
        for name, cam in items.items():
            if cam.name is None:
                cam.name = name
        self.cameras: dict[str, Camera] = items

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras.values())

    def __getitem__(self, key: str | int) -> Camera:
        if isinstance(key, (int, np.integer)):
            return list(self.cameras.values())[key]
        try:
            return self.cameras[key]
        except KeyError:
            raise KeyError(f"no camera {key!r} in the rig; cameras: {self.names}") from None

    def __repr__(self) -> str:
        return f"CameraGroup({self.names})"

    @property
    def names(self) -> list[str]:
        """Camera names in view order."""
        return list(self.cameras)

    @classmethod
    def from_config(
        cls, config: HasCameraTable, image_sizes: Mapping[str, tuple[int, int]] | None = None
    ) -> CameraGroup:
        """:meth:`from_table` of ``config.camera_table()`` -> ``(defaults, specs)``."""
        defaults, specs = config.camera_table()
        return cls.from_table(specs, defaults, image_sizes)

    @classmethod
    def from_table(
        cls,
        specs: Mapping[str, Mapping | None],
        defaults: Mapping | None = None,
        image_sizes: Mapping[str, tuple[int, int]] | None = None,
    ) -> CameraGroup:
        """Build the rig from ``camera name -> spec`` in view order, each merged over ``defaults``
        (``cameras.defaults``); ConfigError without cameras or on a bad spec. A camera that sets its
        own ``rvec``/``tvec`` ignores orbit keys inherited from the defaults; setting both in the
        camera's own table is an error. ``image_sizes``: ``view -> (height, width)`` of footage."""
        defaults = dict(defaults or {})
        image_sizes = image_sizes or {}
        if not specs:
            raise ConfigError(
                "cameras: the config defines no cameras (add [cameras.<name>] tables)"
            )
        cameras = {}
        for name, own in specs.items():
            own = dict(own or {})
            explicit = [k for k in EXPLICIT_KEYS if k in own]
            orbit = [k for k in ORBIT_KEYS if k in own]
            if explicit and orbit:
                raise ConfigError(
                    f"cameras.{name}: sets both {explicit} and orbit keys {orbit}; use one"
                )
            base = defaults
            if explicit:
                base = {k: v for k, v in defaults.items() if k not in ORBIT_KEYS}
            elif orbit:
                base = {k: v for k, v in defaults.items() if k not in EXPLICIT_KEYS}
            cameras[name] = Camera.from_spec(
                {**base, **own}, name=name, image_size=image_sizes.get(name)
            )
        return cls(cameras)

    @classmethod
    def from_arrays(
        cls,
        names: Iterable[str],
        rvecs: Float[np.ndarray, "V 3"],
        tvecs: Float[np.ndarray, "V 3"],
        intrs: Float[np.ndarray, "V 4"],
        dists: Float[np.ndarray, "V K"],
    ) -> CameraGroup:
        """Build a rig from stacked arrays ``(V, 3)``, ``(V, 3)``, ``(V, 4)``, ``(V, K)``."""
        names = list(names)
        arrays = [np.asarray(a, dtype=np.float64) for a in (rvecs, tvecs, intrs, dists)]
        for a in arrays:
            if a.shape[0] != len(names):
                raise ValueError(f"{len(names)} names but an array has shape {a.shape}")
        rvecs, tvecs, intrs, dists = arrays
        return cls(
            {
                name: Camera(rvec=rvecs[i], tvec=tvecs[i], intr=intrs[i], dist=dists[i], name=name)
                for i, name in enumerate(names)
            }
        )

    def subset(self, names: Iterable[str]) -> CameraGroup:
        """A new rig with the cameras ``names``, in that order (cameras are shared)."""
        return CameraGroup({name: self[name] for name in names})

    @property
    def rvecs(self) -> Float[np.ndarray, "V 3"]:
        """``(V, 3)``."""
        return np.stack([c.rvec for c in self])

    @property
    def tvecs(self) -> Float[np.ndarray, "V 3"]:
        """``(V, 3)``."""
        return np.stack([c.tvec for c in self])

    @property
    def intrs(self) -> Float[np.ndarray, "V 4"]:
        """``(V, 4)`` as ``[fx, fy, cx, cy]``."""
        return np.stack([c.intr for c in self])

    @property
    def dists(self) -> Float[np.ndarray, "V K"]:
        """``(V, K)``, zero-padded to the longest camera's ``K``."""
        k = max((c.dist.size for c in self), default=0)
        out = np.zeros((len(self), k))
        for i, c in enumerate(self):
            out[i, : c.dist.size] = c.dist
        return out

    @property
    def rmats(self) -> Float[np.ndarray, "V 3 3"]:
        """``(V, 3, 3)``."""
        return camera_model.rvec_to_rmat_numpy(self.rvecs)

    @property
    def pmats(self) -> Float[np.ndarray, "V 3 4"]:
        """``(V, 3, 4)`` projection matrices ``K [R | t]`` (ignore distortion)."""
        kmats = camera_model.intr_to_kmat_numpy(self.intrs)
        return kmats @ np.concatenate([self.rmats, self.tvecs[:, :, None]], axis=2)

    @property
    def positions(self) -> Float[np.ndarray, "V 3"]:
        """``(V, 3)`` camera centres."""
        return np.stack([c.position for c in self])

    def project(self, pts3d: Float[np.ndarray, "*pts 3"]) -> Float[np.ndarray, "V *pts 2"]:
        """Project world points ``(*pts, 3)`` through every camera -> ``(V, *pts, 2)``."""
        return camera_model.project_numpy(pts3d, self.rmats, self.tvecs, self.intrs, self.dists)

    def undistort_points(
        self, pts2d: Float[np.ndarray, "V *pts 2"]
    ) -> Float[np.ndarray, "V *pts 2"]:
        """Remove lens distortion from pixels ``(V, *pts, 2)`` (same intrinsics, no distortion)."""
        pts2d = np.asarray(pts2d, dtype=np.float64)
        if not np.any(self.dists):
            return pts2d
        out = np.array(pts2d)
        for v, cam in enumerate(self):
            if not np.any(cam.dist):
                continue
            fx, fy, cx, cy = cam.intr
            flat = pts2d[v].reshape(-1, 2)
            norm = (flat - [cx, cy]) / [fx, fy]
            und = camera_model.undistort_normalized(norm, cam.dist)
            out[v] = (und * [fx, fy] + [cx, cy]).reshape(pts2d[v].shape)
        return out

    def triangulate(
        self,
        pts2d: Float[np.ndarray, "V *pts 2"],
        weights: Float[np.ndarray, " V *pts"] | None = None,
        *,
        chunk_points: int | None = None,
    ) -> Float[np.ndarray, "*pts 3"]:
        """Weighted NaN-aware DLT (:func:`flylib.camera.jax_model.triangulate_dlt`) of pixels
        ``(V, *pts, 2)`` -> ``(*pts, 3)``, NaN below two views; a weight ``(V, *pts)`` <= 0 or
        non-finite drops the view. Undistorts first, then runs fixed-length chunks through one
        jitted kernel (JAX imported on the first call); wrong shapes are a ValueError."""
        from .jax_model import DLT_CHUNK_POINTS, triangulate_dlt_chunked

        pts2d = np.asarray(pts2d, dtype=np.float64)
        if pts2d.ndim < 2 or pts2d.shape[-1] != 2:
            raise ValueError(f"pts2d must be (V, *pts, 2), got shape {pts2d.shape}")
        self._check_views(pts2d)
        if weights is not None:
            weights = np.asarray(weights, dtype=np.float64)
            if weights.shape != pts2d.shape[:-1]:
                raise ValueError(
                    f"weights must have shape {pts2d.shape[:-1]} (V, *pts), got {weights.shape}"
                )
        return triangulate_dlt_chunked(
            self.undistort_points(pts2d),
            self.pmats,
            weights,
            DLT_CHUNK_POINTS if chunk_points is None else chunk_points,
        )

    def backproject_ray(
        self, pixels: Float[np.ndarray, "V 2"]
    ) -> tuple[Float[np.ndarray, "V 3"], Float[np.ndarray, "V 3"]]:
        """World rays of one pixel per camera ``(V, 2)`` -> origins, directions ``(V, 3)``."""
        pixels = np.asarray(pixels, dtype=np.float64)
        self._check_views(pixels)
        rays = [cam.backproject_ray(p) for cam, p in zip(self, pixels)]
        return np.stack([r[0] for r in rays]), np.stack([r[1] for r in rays])

    def _check_views(self, arr: np.ndarray) -> None:
        if arr.shape[0] != len(self):
            raise ValueError(
                f"array has {arr.shape[0]} views on axis 0 but the rig has {len(self)} "
                f"cameras {self.names}"
            )
