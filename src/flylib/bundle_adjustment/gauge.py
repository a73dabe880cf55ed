"""The similarity gauge of bundle adjustment: what to hold during a fit, how to report.

With no extrinsic parameter fixed, a similarity of the whole scene (rotation,
translation, scale: 7 directions) changes no image. Levenberg-Marquardt converges only
linearly along such directions, so the fit holds one camera's pose and one translation
entry (:func:`gauge_refs`); afterwards the result is mapped into the similarity frame
closest to the initial rig (:func:`align_gauge`), independent of which were held.
"""

from __future__ import annotations

import numpy as np

from ..camera_model import rmat_to_rvec_numpy, rvec_to_rmat_numpy


def untied_extrinsics(layout) -> bool:
    ext = layout.var_index[:, :6].ravel()
    return np.unique(ext).size == ext.size


def gauge_refs(table: np.ndarray, names) -> list[str]:
    """References that pin the similarity gauge: the first camera's pose and, for scale,
    the translation entry of the camera farthest from it that scaling moves most."""
    rmats = rvec_to_rmat_numpy(table[:, 0:3])
    centres = -np.einsum("vji,vj->vi", rmats, table[:, 3:6])
    far = int(np.argmax(np.linalg.norm(centres - centres[0], axis=1)))
    if far == 0:
        return [f"{names[0]}.rvec", f"{names[0]}.tvec"]
    d_tvec = -rmats[far] @ (centres[far] - centres[0])
    return [f"{names[0]}.rvec", f"{names[0]}.tvec",
            f"{names[far]}.tvec[{int(np.argmax(np.abs(d_tvec)))}]"]


def _camera_anchors(table: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """Each camera's centre and the point ``depths[v]`` ahead on its optical axis.

    Returns ``(2V, 3)``: centres first, then the viewing targets.
    """
    rmats = rvec_to_rmat_numpy(table[:, 0:3])
    centres = -np.einsum("vji,vj->vi", rmats, table[:, 3:6])
    targets = centres + depths[:, None] * rmats[:, 2]
    return np.concatenate([centres, targets])


def align_gauge(table0: np.ndarray, table: np.ndarray, pts: np.ndarray):
    """Map the refined rig + points by the similarity that best restores the initial rig.

    Umeyama's least-squares similarity between the two rigs' camera centres *and*
    viewing targets (a point at the initial camera distance along each optical axis).
    Centres alone leave a near-gauge free: with long lenses far from the fly, moving
    the fly sideways while every camera turns to follow it barely changes any image,
    so the solution would drift; the targets pin where the rig looks.
    ``X' = s R X + t`` for points, and per camera ``R_c' = R_c R^T``,
    ``t_c' = s t_c - R_c' t`` (projections are unchanged).
    """
    if len(table) < 2:
        return table, pts
    depths = np.linalg.norm(table0[:, 3:6], axis=1)
    src, dst = _camera_anchors(table, depths), _camera_anchors(table0, depths)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    var_s = (a ** 2).sum() / len(src)
    if var_s <= 0:
        return table, pts
    scale = np.trace(np.diag(sig) @ d) / var_s
    shift = mu_d - scale * rot @ mu_s
    out = table.copy()
    for v, rmat in enumerate(rvec_to_rmat_numpy(table[:, 0:3])):
        rc = rmat @ rot.T
        out[v, 0:3] = rmat_to_rvec_numpy(rc)
        out[v, 3:6] = scale * table[v, 3:6] - rc @ shift
    return out, (scale * pts @ rot.T + shift)

