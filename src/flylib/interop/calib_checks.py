"""Checks every calibration value read from another tool's file, with messages naming the file, the
camera section and the key: a value that is text, the wrong shape, NaN or infinite would otherwise
surface far from the file (a solver's "initial guess outside bounds", NaN points, an error naming
another camera)."""

from __future__ import annotations

import numpy as np

from ..camera.model import N_DIST_COEFFS
from ..errors import ImportFormatError

_DIST_TEXT = (
    f"at most {N_DIST_COEFFS} OpenCV-order distortion coefficients "
    "(k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]])"
)


def _describe(value) -> str:
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} and dtype {value.dtype}"
    text = " ".join(repr(value).split())
    return f"a {type(value).__name__} ({text[:40]}{'...' if len(text) > 40 else ''})"


def numeric_array(value, where: str, key: str, fix: str) -> np.ndarray:
    """``value`` (a NumPy array of booleans/integers/floats, or nested lists of numbers) as a
    float64 array; text, objects or ragged nesting are an :class:`ImportFormatError` naming
    ``where`` and ``key``, with ``fix`` as the remedy."""
    if isinstance(value, (str, bytes, dict)):
        raise ImportFormatError(f"{where}: {key!r} is {_describe(value)}, not numbers; {fix}")
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, OverflowError) as exc:  # ragged nesting, huge integers
        raise ImportFormatError(f"{where}: {key!r} is not a regular array ({exc}); {fix}") from None
    if arr.dtype.kind not in "biuf":
        raise ImportFormatError(f"{where}: {key!r} is {_describe(value)}, not numbers; {fix}")
    return arr.astype(np.float64)


def camera_value(value, kind: str, where: str, key: str) -> np.ndarray:
    """One camera's calibration value, checked (numbers, its shape or count, all finite) and
    returned as float64 ``(3, 3)``, ``(3,)`` or ``(K,)``.

    ``kind``: ``"matrix"`` (3x3 K with positive focal lengths, no skew), ``"rotmat"`` (3x3
    rotation), ``"vec3"`` (3 numbers) or ``"dist"`` (0..12 OpenCV coefficients). ``where`` (the file
    and camera section, ``"calib.toml [cam_2] (name 'rh')"``) and ``key`` (the file's key,
    ``"distortions"``) are named in the one-line :class:`ImportFormatError`."""
    what = {
        "matrix": "a 3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]",
        "rotmat": "a 3x3 rotation matrix",
        "vec3": "3 numbers",
        "dist": _DIST_TEXT,
    }[kind]
    arr = numeric_array(value, where, key, f"it must be {what}")
    shape = {"matrix": (3, 3), "rotmat": (3, 3), "vec3": (3,)}.get(kind)
    if shape is None:
        arr = arr.ravel()
        if arr.size > N_DIST_COEFFS:
            raise ImportFormatError(f"{where}: {key!r} has {arr.size} values; it must be {what}")
    elif arr.size != int(np.prod(shape)):
        raise ImportFormatError(f"{where}: {key!r} has shape {arr.shape}; it must be {what}")
    else:
        arr = arr.reshape(shape)
    if not np.isfinite(arr).all():
        raise ImportFormatError(
            f"{where}: {key!r} holds NaN or infinite values; it must be {what}, all finite"
        )
    if kind == "matrix":
        skewed = abs(arr[0, 1]) > 1e-12 * abs(arr[0, 0]) or arr[1, 0] != 0
        if skewed or arr[0, 0] <= 0 or arr[1, 1] <= 0 or not np.allclose(arr[2], [0.0, 0.0, 1.0]):
            raise ImportFormatError(
                f"{where}: {key!r} is {arr.tolist()}; it must be {what} with fx, fy > 0"
            )
    if kind == "rotmat" and (
        not np.allclose(arr @ arr.T, np.eye(3), atol=1e-4) or np.linalg.det(arr) <= 0
    ):
        raise ImportFormatError(
            f"{where}: {key!r} is not a rotation (R R^T != I or det R <= 0); it must be {what}"
        )
    return arr


def image_size(value, where: str, key: str = "size") -> tuple[int, int]:
    """Anipose's ``size = [width, height]``: two positive integers."""
    ok = (
        isinstance(value, (list, tuple))
        and len(value) == 2
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        and all(np.isfinite(v) and v > 0 and float(v) == int(v) for v in value)
    )
    if not ok:
        raise ImportFormatError(
            f"{where}: {key!r} is {value!r}; it must be [width, height] in pixels (two positive integers)"
        )
    return int(value[0]), int(value[1])
