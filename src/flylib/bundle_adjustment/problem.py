"""The least-squares core: residuals, the JAX Jacobian assembled as a sparse matrix.

Unknowns are ``[free camera variables, 3D points (N, 3)]``. Each observation ``m`` (view
``v``, point ``n``) contributes two residual rows ``w_m * (project(X_n; camera_v) - xy_m)``;
its Jacobian block is ``jax.jacfwd`` of ``project_full_one`` in the point and the camera row,
``vmap``-ed and jitted once for a fixed chunk of rows (residuals use a NumPy twin: no
compilation). Camera columns go through :class:`~.params.ParamLayout` (fixed entries dropped,
tied ones summed). Bone rows add one row per (frame, bone), toward fixed targets or, with
``bone_group``, unknown lengths shared by every frame of a bone."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse

from ..camera import jax_model, model as camera_model  # jax_model: JAX float64, CPU, compile cache
from .params import ParamLayout

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float, Int
    from scipy.optimize import OptimizeResult

# Fixed-size chunks: one compilation serves every problem size, and a chunk stays in cache.
CHUNK = 2048


@cache
def _jacobian_kernel():
    """Jitted ``(points (M,3), camera rows (M,C)) -> (projections, d/dpoint, d/drow)``."""
    import jax

    def project_row(pt, row):
        return jax_model.project_full_one(pt, row[0:3], row[3:6], row[6:10], row[10:])

    def project_with_jac(pt, row):
        value = project_row(pt, row)
        jpt, jrow = jax.jacfwd(project_row, argnums=(0, 1))(pt, row)
        return value, jpt, jrow

    return jax.jit(jax.vmap(project_with_jac))


def _pad(a: np.ndarray, size: int) -> np.ndarray:
    if a.shape[0] == size:
        return a
    pad = np.repeat(a[:1], size - a.shape[0], axis=0)
    return np.concatenate([a, pad], axis=0)


def project_rows(
    pts: Float[np.ndarray, "M 3"], rows: Float[np.ndarray, "M C"]
) -> Float[np.ndarray, "M 2"]:
    """Project ``pts`` ``(M, 3)`` through per-observation camera rows ``(M, C)``: the NumPy twin
    of :func:`flylib.camera.jax_model.project_full_one`, so residuals need no compilation."""
    if pts.shape[0] == 0:
        return np.zeros((0, 2))
    cam = np.einsum("mij,mj->mi", camera_model.rvec_to_rmat_numpy(rows[:, 0:3]), pts) + rows[:, 3:6]
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    dist = rows[:, 10:]
    if dist.shape[1] and np.any(dist):
        d = camera_model.pad_dist_numpy(dist)
        radial, add_x, add_y = camera_model.distortion_terms(x, y, d.T)
        x, y = x * radial + add_x, y * radial + add_y
    return np.stack([rows[:, 6] * x + rows[:, 8], rows[:, 7] * y + rows[:, 9]], axis=-1)


def project_rows_with_jac(
    pts: Float[np.ndarray, "M 3"], rows: Float[np.ndarray, "M C"]
) -> tuple[Float[np.ndarray, "M 2"], Float[np.ndarray, "M 2 3"], Float[np.ndarray, "M 2 C"]]:
    """Projections ``(M, 2)`` and Jacobians ``(M, 2, 3)`` / ``(M, 2, C)``."""
    m = pts.shape[0]
    value, jpt = np.empty((m, 2)), np.empty((m, 2, 3))
    jrow = np.empty((m, 2, rows.shape[1]))
    project_jac = _jacobian_kernel()
    for lo in range(0, m, CHUNK):
        hi = min(lo + CHUNK, m)
        out = project_jac(_pad(pts[lo:hi], CHUNK), _pad(rows[lo:hi], CHUNK))
        for dst, src in zip((value, jpt, jrow), out):
            dst[lo:hi] = np.asarray(src)[: hi - lo]
    return value, jpt, jrow


@dataclass
class Problem:
    """One bundle-adjustment problem over ``N`` points and ``M`` observations. ``table0`` is the
    initial ``(V, C)`` camera table; ``view``, ``point``, ``weight`` (residual scale, ``sqrt(conf)``
    or 1) are ``(M,)``, ``xy`` ``(M, 2)`` pixels. Bone rows ``(B,)`` join points ``bone_i``,
    ``bone_j``; ``bone_weight`` is pixels per unit of relative deviation:
    ``bone_weight * (|Xi - Xj| - target) / target`` with ``bone_group=None`` (fixed targets), else
    ``bone_weight * (|Xi - Xj| / L - 1)`` for the shared unknown length ``L`` of the row's group
    (scale free: a similarity of the whole scene leaves it unchanged)."""

    table0: Float[np.ndarray, "V C"]
    layout: ParamLayout
    view: Int[np.ndarray, " M"]
    point: Int[np.ndarray, " M"]
    xy: Float[np.ndarray, "M 2"]
    weight: Float[np.ndarray, " M"]
    n_points: int
    bone_i: Int[np.ndarray, " B"]
    bone_j: Int[np.ndarray, " B"]
    bone_target: Float[np.ndarray, " B"]
    bone_weight: float = 0.0
    bone_group: Int[np.ndarray, " B"] | None = None

    def __post_init__(self):
        self.n_cam = self.layout.n_free
        self.n_obs = self.view.size
        self.n_bones = self.bone_i.size if self.bone_weight > 0 else 0
        free_lengths = self.n_bones and self.bone_group is not None
        self.n_len = int(self.bone_group.max()) + 1 if free_lengths else 0
        self.shape = (2 * self.n_obs + self.n_bones, self.n_cam + 3 * self.n_points + self.n_len)
        self._build_structure()

    def pack(
        self, table: Float[np.ndarray, "V C"], pts3d: Float[np.ndarray, "N 3"]
    ) -> Float[np.ndarray, " X"]:
        parts = [self.layout.pack(table), np.asarray(pts3d, float).ravel()]
        if self.n_len:
            sums = np.bincount(self.bone_group, self.bone_target, self.n_len)
            parts.append(sums / np.maximum(np.bincount(self.bone_group, minlength=self.n_len), 1))
        return np.concatenate(parts)

    def unpack(
        self, x: Float[np.ndarray, " X"]
    ) -> tuple[Float[np.ndarray, "V C"], Float[np.ndarray, "N 3"]]:
        table = self.layout.unpack(x[: self.n_cam], self.table0)
        return table, x[self.n_cam : self.n_cam + 3 * self.n_points].reshape(self.n_points, 3)

    def _lengths(self, x: np.ndarray) -> np.ndarray:
        if self.n_len:
            return x[self.n_cam + 3 * self.n_points :][self.bone_group]
        return self.bone_target

    def residuals(self, x: Float[np.ndarray, " X"]) -> Float[np.ndarray, " R"]:
        table, pts = self.unpack(x)
        proj = project_rows(pts[self.point], table[self.view])
        r_obs = (self.weight[:, None] * (proj - self.xy)).ravel()
        if not self.n_bones:
            return r_obs
        return np.concatenate([r_obs, self._bone_residuals(pts, self._lengths(x))])

    def _bone_residuals(self, pts: np.ndarray, target: np.ndarray) -> np.ndarray:
        length = np.linalg.norm(pts[self.bone_i] - pts[self.bone_j], axis=1)
        if self.n_len:  # relative to the unknown itself: scale-free, so no pull to shrink
            return self.bone_weight * (length / target - 1.0)
        return self.bone_weight * (length - target) / self.bone_target

    def jacobian(self, x: Float[np.ndarray, " X"]) -> scipy.sparse.csr_matrix:
        table, pts = self.unpack(x)
        _, jpt, jrow = project_rows_with_jac(pts[self.point], table[self.view])
        w = self.weight[:, None, None]
        parts = [
            (w * jpt).ravel(),
            (w * jrow)[self._cam_m, :, self._cam_c].T.ravel() if self._cam_m.size else np.zeros(0),
        ]
        if self.n_bones:
            diff = pts[self.bone_i] - pts[self.bone_j]
            length = np.maximum(np.linalg.norm(diff, axis=1), 1e-12)
            scale = self._lengths(x)
            g = (self.bone_weight / scale / length)[:, None] * diff
            parts += [g.ravel(), (-g).ravel()]
            if self.n_len:
                parts.append(-self.bone_weight * length / scale**2)
        data = np.concatenate(parts)[self._order]
        data = np.add.reduceat(data, self._starts) if data.size else data
        return scipy.sparse.csr_matrix((data, self._indices, self._indptr), shape=self.shape)

    def sparsity(self) -> scipy.sparse.csr_matrix:
        """The Jacobian's structural non-zeros (for ``jac_sparsity`` with finite differences)."""
        ones = np.ones(self._indices.size)
        return scipy.sparse.csr_matrix((ones, self._indices, self._indptr), shape=self.shape)

    def _build_structure(self):
        m = np.arange(self.n_obs)
        # point block: rows 2m + a, columns n_cam + 3 * point + b, in (m, a, b) order
        rows_pt = (2 * m[:, None, None] + np.arange(2)[None, :, None]).repeat(3, axis=2)
        cols_pt = np.broadcast_to(
            self.n_cam + 3 * self.point[:, None, None] + np.arange(3)[None, None, :],
            (self.n_obs, 2, 3),
        )
        # camera block: every free column of the observation's view, (entry, a) order
        var = self.layout.var_index[self.view]  # (M, C)
        self._cam_m, self._cam_c = np.nonzero(var >= 0)
        cam_var = var[self._cam_m, self._cam_c]
        rows_cam = np.stack([2 * self._cam_m, 2 * self._cam_m + 1], axis=0).ravel()
        cols_cam = np.concatenate([cam_var, cam_var])
        rows = [rows_pt.ravel(), rows_cam]
        cols = [cols_pt.ravel(), cols_cam]
        if self.n_bones:
            b = 2 * self.n_obs + np.arange(self.n_bones)
            rows += [np.repeat(b, 3), np.repeat(b, 3)]
            cols += [
                (self.n_cam + 3 * self.bone_i[:, None] + np.arange(3)).ravel(),
                (self.n_cam + 3 * self.bone_j[:, None] + np.arange(3)).ravel(),
            ]
            if self.n_len:
                rows.append(b)
                cols.append(self.n_cam + 3 * self.n_points + self.bone_group)
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        key = rows.astype(np.int64) * self.shape[1] + cols
        self._order = np.argsort(key, kind="stable")
        unique, self._starts = np.unique(key[self._order], return_index=True)
        self._indices = (unique % self.shape[1]).astype(np.int64)
        counts = np.bincount((unique // self.shape[1]).astype(np.int64), minlength=self.shape[0])
        self._indptr = np.concatenate([[0], np.cumsum(counts)])

    def solve(
        self, table: Float[np.ndarray, "V C"], pts3d: Float[np.ndarray, "N 3"], **kwargs
    ) -> OptimizeResult:
        """``scipy.optimize.least_squares`` from ``(table, pts3d)``; kwargs pass through. ``jac``
        defaults to the JAX Jacobian; finite differences (``"2-point"``...) get ``jac_sparsity``."""
        options = {"method": "trf", "x_scale": "jac", "tr_solver": "lsmr"}
        options.update(kwargs)
        if options.get("jac", "jax") == "jax":
            options["jac"] = self.jacobian
        elif options["jac"] in ("2-point", "3-point", "cs"):
            options.setdefault("jac_sparsity", self.sparsity())
        if options["method"] == "lm":  # MINPACK cannot take a sparse Jacobian
            options.pop("tr_solver", None)
            jac = options["jac"]
            if callable(jac):
                options["jac"] = lambda x: jac(x).toarray()
        from scipy.optimize import least_squares  # only this solver: its import costs ~0.4 s

        return least_squares(self.residuals, self.pack(table, pts3d), **options)
