"""Drawing primitives: 2D skeleton overlays and depth-ordered 3D skeletons, with OpenCV.

All draw in place on an ``(H, W, 3)`` uint8 image (maybe a strided view) in its pixels, integers
being pixel centres, colours in its channel order (RGB in flylib); NaN points and bones are skipped.
"""

from __future__ import annotations

import cv2
import numpy as np

from .specs import parse_color

#: Fractional bits of the fixed-point coordinates passed to OpenCV (1/16 px).
_SHIFT = 4
_ONE = 1 << _SHIFT
#: Coordinates beyond this (degenerate projections) would overflow OpenCV's fixed point: not drawn.
_MAX_COORD = 1e6


def limb_colors(skeleton, overrides: dict | None = None) -> np.ndarray:
    """``(n_limbs, 3)`` uint8 RGB per limb: ``overrides``, the skeleton's ``palette``, ``tab10``."""
    overrides = overrides or {}
    palette = dict(getattr(skeleton, "palette", {}) or {})
    out = np.zeros((len(skeleton.limb_names), 3), np.uint8)
    for i, limb in enumerate(skeleton.limb_names):
        if limb in overrides:
            out[i] = overrides[limb]
        elif limb in palette:
            out[i] = parse_color(palette[limb], f"skeleton.limb_palette.{limb}")
        else:  # only here matplotlib: a job pays ~0.2 s to import it
            from matplotlib import colormaps

            out[i] = np.round(np.array(colormaps["tab10"](i % 10)[:3]) * 255)
    return out


def skeleton_colors(skeleton, overrides: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(P, 3)`` and ``(B, 3)`` uint8 RGB: each point's limb colour (grey for no limb), and the
    colour of each bone's first endpoint's limb."""
    # a point in no limb (limb_id -1) indexes the grey row appended last
    limbs = np.vstack([limb_colors(skeleton, overrides), [[128, 128, 128]]]).astype(np.uint8)
    limb_id = np.asarray(skeleton.limb_id, dtype=int)
    bones = np.asarray(skeleton.bones, dtype=int).reshape(-1, 2)
    return limbs[limb_id], limbs[limb_id[bones[:, 0]]]


def _fixed(xy: np.ndarray) -> np.ndarray:
    """Fixed-point integer coordinates for OpenCV's ``shift`` argument."""
    scaled = np.round(np.asarray(xy, float) * _ONE)
    return np.where(np.isfinite(scaled), scaled, 0).astype(np.int64)


def _drawable(xy: np.ndarray) -> np.ndarray:
    return np.isfinite(xy).all(axis=-1) & (np.abs(xy) < _MAX_COORD).all(axis=-1)


def color_tuples(colors) -> list[tuple[int, int, int]]:
    """``(N, 3)`` colours as the int tuples OpenCV takes (a list passes through)."""
    if isinstance(colors, list):
        return colors
    return [(int(c[0]), int(c[1]), int(c[2])) for c in np.asarray(colors)]


def draw_points(img: np.ndarray, xy: np.ndarray, colors: np.ndarray, radius: int) -> None:
    """Draw filled, anti-aliased discs at ``xy`` ``(P, 2)`` in ``colors`` ``(P, 3)``."""
    if radius <= 0:
        return
    colors = color_tuples(colors)
    fixed = _fixed(xy).tolist()
    for p in np.flatnonzero(_drawable(xy)).tolist():
        cv2.circle(img, fixed[p], radius * _ONE, colors[p], -1, cv2.LINE_AA, _SHIFT)


def draw_rings(
    img: np.ndarray,
    xy: np.ndarray,
    mask: np.ndarray,
    radius: int,
    color: tuple[int, int, int] = (255, 255, 255),
) -> None:
    """Circle the points ``xy[mask]`` (e.g. points a person corrected) with thin rings."""
    fixed = _fixed(xy).tolist()
    for p in np.flatnonzero(_drawable(xy) & np.asarray(mask, bool)).tolist():
        cv2.circle(img, fixed[p], max(radius, 1) * 2 * _ONE + _ONE, color, 1, cv2.LINE_AA, _SHIFT)


def draw_bones(
    img: np.ndarray, xy: np.ndarray, bones: np.ndarray, colors: np.ndarray, thickness: int
) -> None:
    """Draw anti-aliased segments between ``xy[bones[:, 0]]`` and ``xy[bones[:, 1]]``."""
    colors = color_tuples(colors)
    bones = np.asarray(bones, dtype=int).reshape(-1, 2)
    ok = _drawable(xy)
    fixed = _fixed(xy).tolist()
    for b in np.flatnonzero(ok[bones[:, 0]] & ok[bones[:, 1]]).tolist():
        i, j = bones[b]
        cv2.line(img, fixed[i], fixed[j], colors[b], thickness, cv2.LINE_AA, _SHIFT)


def draw_skeleton_2d(
    img: np.ndarray,
    xy: np.ndarray,
    bones: np.ndarray,
    point_colors: np.ndarray,
    bone_colors: np.ndarray,
    *,
    radius: int = 3,
    thickness: int = 2,
) -> None:
    """Draw a 2D skeleton ``xy`` ``(P, 2)`` on ``img``: bones ``(B, 2)`` first, joints on top.

    ``point_colors`` ``(P, 3)`` and ``bone_colors`` ``(B, 3)``; ``radius`` 0 draws no joints."""
    draw_bones(img, xy, bones, bone_colors, thickness)
    draw_points(img, xy, point_colors, radius)


def draw_skeleton_3d(
    img: np.ndarray,
    xy: np.ndarray,
    depth: np.ndarray,
    bones: np.ndarray,
    point_colors: np.ndarray,
    bone_colors: np.ndarray,
    *,
    radius: int = 3,
    thickness: int = 2,
) -> None:
    """Draw a reprojected 3D skeleton back to front by camera-frame ``depth`` ``(P,)`` (a bone at
    its endpoints' mean), so nearer parts cover farther ones; nothing behind the camera is drawn.
    The other arguments are :func:`draw_skeleton_2d`'s."""
    ok = _drawable(xy) & np.isfinite(depth) & (depth > 0)
    fixed = _fixed(xy).tolist()
    point_colors, bone_colors = color_tuples(point_colors), color_tuples(bone_colors)
    bones = np.asarray(bones, dtype=int).reshape(-1, 2)
    visible_bones = np.flatnonzero(ok[bones[:, 0]] & ok[bones[:, 1]])
    joints = np.flatnonzero(ok) if radius > 0 else np.zeros(0, int)
    # bones then joints: a stable sort on decreasing depth paints bones first at equal depth
    depths = np.concatenate(
        [0.5 * (depth[bones[visible_bones, 0]] + depth[bones[visible_bones, 1]]), depth[joints]]
    )
    order = np.argsort(-depths, kind="stable")
    n_bones = len(visible_bones)
    for k in order.tolist():
        if k < n_bones:
            b = visible_bones[k]
            i, j = bones[b]
            cv2.line(img, fixed[i], fixed[j], bone_colors[b], thickness, cv2.LINE_AA, _SHIFT)
        else:
            p = joints[k - n_bones]
            cv2.circle(img, fixed[p], radius * _ONE, point_colors[p], -1, cv2.LINE_AA, _SHIFT)


def to_panel_coords(
    xy: np.ndarray, image_hw: tuple[int, int], panel_wh: tuple[int, int]
) -> np.ndarray:
    """Raw-frame pixels into a panel showing the frame resized (``cv2.resize``'s alignment)."""
    img_h, img_w = image_hw
    w, h = panel_wh
    sx, sy = w / img_w, h / img_h
    out = np.empty_like(xy, dtype=float)
    out[..., 0] = (xy[..., 0] + 0.5) * sx - 0.5
    out[..., 1] = (xy[..., 1] + 0.5) * sy - 0.5
    return out


#: View names and the frame stamp: light on a dark outline, readable over any footage.
LABEL_FONT = cv2.FONT_HERSHEY_SIMPLEX
LABEL_SCALE = 0.5
LABEL_MARGIN = 6


def draw_label(image: np.ndarray, text: str, corner: str = "top-left") -> None:
    """Write one line of ASCII ``text`` in a corner of ``image``, white on a black outline."""
    (width, height), baseline = cv2.getTextSize(text, LABEL_FONT, LABEL_SCALE, 1)
    x = LABEL_MARGIN
    y = LABEL_MARGIN + height if corner == "top-left" else image.shape[0] - LABEL_MARGIN - baseline
    for color, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(
            image, text, (x, y), LABEL_FONT, LABEL_SCALE, color, thickness, lineType=cv2.LINE_AA
        )
