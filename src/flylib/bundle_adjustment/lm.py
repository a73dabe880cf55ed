"""Levenberg-Marquardt on the reduced camera system (Schur complement).

The unknowns of a :class:`~.problem.Problem` split into *global* ones, few and seen by many
observations (the free camera parameters, the points shared by every frame such as a tethered fly's
rigid thorax-coxa points, the bone lengths), and *local* ones: every other 3D point. Points joined
by a bone-length residual are coupled, so the local unknowns form small blocks (one point, 3x3,
without bones; one frame of a leg chain, e.g. 12x12, with them) coupled only through the global
unknowns. Each step solves ``(J^T J + lambda D) dx = -J^T r`` by eliminating the local blocks
(batched dense inverses), solving the dense reduced system of the global unknowns (~100), and
back-substituting. Robust losses (scipy's) are applied by iteratively reweighted least squares."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.sparse.csgraph import connected_components

from .problem import Problem

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

log = logging.getLogger(__name__)


class OptimizeResult(dict):
    """scipy.optimize's result, a dict read by attribute (importing scipy.optimize: ~0.4 s a job)."""

    def __getattr__(self, name: str):  # a missing key: AttributeError, as scipy's
        return self[name] if name in self else super().__getattribute__(name)


LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


@dataclass
class BlockStructure:
    """Column partition of a problem: ``global_cols`` ``(G,)`` of the global unknowns,
    ``block_cols`` ``(B, S)`` of each local block, ``-1`` where padded."""

    global_cols: np.ndarray
    block_cols: np.ndarray


def block_structure(
    problem: Problem, global_points: Bool[np.ndarray, " N"] | None = None
) -> BlockStructure:
    """Global columns and local blocks of ``problem``: points not ``global_points`` ``(N,)`` are
    local, grouped with the points they share a bone residual with."""
    n_pts = problem.n_points
    is_global = np.zeros(n_pts, bool) if global_points is None else np.asarray(global_points, bool)
    n_cam = problem.n_cam
    pt_cols = n_cam + 3 * np.arange(n_pts)[:, None] + np.arange(3)
    length_cols = n_cam + 3 * n_pts + np.arange(problem.n_len)
    global_cols = np.concatenate([np.arange(n_cam), pt_cols[is_global].ravel(), length_cols])

    local = np.flatnonzero(~is_global)
    if problem.n_bones:
        bi, bj = problem.bone_i, problem.bone_j
        both = ~is_global[bi] & ~is_global[bj]
        graph = scipy.sparse.coo_matrix(
            (np.ones(both.sum()), (bi[both], bj[both])), shape=(n_pts, n_pts)
        )
        _, label = connected_components(graph, directed=False)
    else:
        label = np.arange(n_pts)
    label = label[local]
    _, block_of = np.unique(label, return_inverse=True)
    n_blocks = int(block_of.max()) + 1 if local.size else 0
    order = np.argsort(block_of, kind="stable")
    counts = np.bincount(block_of, minlength=n_blocks)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.empty(local.size, int)
    slot[order] = np.arange(local.size) - np.repeat(starts, counts)
    width = int(counts.max()) if n_blocks else 0
    block_cols = np.full((n_blocks, 3 * width), -1)
    for k in range(3):
        block_cols[block_of, 3 * slot + k] = pt_cols[local, k]
    return BlockStructure(global_cols=global_cols, block_cols=block_cols)


def _loss(name: str, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """scipy's ``rho(z)`` and ``rho'(z)`` for ``z = (r / f_scale)^2``."""
    if name == "linear":
        return z, np.ones_like(z)
    if name == "soft_l1":
        t = 1 + z
        return 2 * (np.sqrt(t) - 1), 1 / np.sqrt(t)
    if name == "huber":
        big = z > 1
        sq = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2 * sq - 1, z), np.where(big, 1 / sq, 1.0)
    if name == "cauchy":
        return np.log1p(z), 1 / (1 + z)
    if name == "arctan":
        return np.arctan(z), 1 / (1 + z**2)
    raise ValueError(f"unknown loss {name!r}; use one of {', '.join(LOSSES)}")


class ReducedSystem:
    """The normal equations of one linearization, in reduced (Schur) form."""

    def __init__(
        self, jac: scipy.sparse.csr_matrix, res: Float[np.ndarray, " R"], blocks: BlockStructure
    ):
        csc = jac.tocsc()
        jg = csc[:, blocks.global_cols]
        self.n_global = blocks.global_cols.size
        cols = blocks.block_cols
        n_blocks, width = cols.shape
        padded = cols < 0
        # a selection matrix, not fancy indexing: padded slots, most of a wide block, read nothing
        slot = np.flatnonzero(~padded.ravel())
        select = scipy.sparse.csc_matrix(
            (np.ones(slot.size), (cols.ravel()[slot], slot)), shape=(jac.shape[1], cols.size)
        )
        jl = (csc @ select).tocsc()
        self.u = (jg.T @ jg).toarray()
        self.gg = jg.T @ res
        # W stored flat (G, B * S) for the GEMMs and as blocks (B, G, S) for batched products
        self.w = (jg.T @ jl).toarray()
        self.w_blocks = np.ascontiguousarray(
            self.w.reshape(self.n_global, n_blocks, width).transpose(1, 0, 2)
        )
        v = (jl.T @ jl).tocoo()
        bi, bj = v.row // width, v.col // width
        same = bi == bj
        self.v = np.zeros((n_blocks, width, width))
        np.add.at(self.v, (bi[same], v.row[same] % width, v.col[same] % width), v.data[same])
        self.v[:, np.arange(width), np.arange(width)] += padded  # keep padding invertible
        self.gl = (jl.T @ res).reshape(n_blocks, width)
        self.padded = padded
        self.diag_u = np.maximum(np.diag(self.u).copy(), 1e-12)
        self.diag_v = np.maximum(np.diagonal(self.v, axis1=1, axis2=2).copy(), 1e-12)
        # blocks grouped by true width: inverses and products at their size, not the widest's
        n_used = (~padded).sum(axis=1)
        self.groups = [(np.flatnonzero(n_used == k), int(k)) for k in np.unique(n_used)]

    def schur(self, lam: float) -> tuple[Float[np.ndarray, "G G"], list, list]:
        """``(S, Y, V^-1)`` for damping ``lam`` (Marquardt: ``lam * diag``); ``Y`` and ``V^-1`` per
        group of blocks of one width (``W_g V_g^-1`` as ``(G, B_g * k)`` and ``(B_g, k, k)``)."""
        s = self.u + np.diag(lam * self.diag_u)
        ys, vinvs = [], []
        for idx, k in self.groups:
            vd = self.v[idx, :k, :k].copy()
            vd[:, np.arange(k), np.arange(k)] += lam * self.diag_v[idx, :k]
            vinv = np.linalg.inv(vd)
            w = self.w_blocks[idx, :, :k]  # (B_g, G, k)
            y = np.matmul(w, vinv).transpose(1, 0, 2).reshape(self.n_global, -1)
            s -= y @ w.transpose(1, 0, 2).reshape(self.n_global, -1).T
            ys.append(y)
            vinvs.append(vinv)
        return 0.5 * (s + s.T), ys, vinvs

    def step(self, lam: float) -> tuple[Float[np.ndarray, " G"], Float[np.ndarray, "B S"]]:
        """``(dx_global, dx_local (B, S))`` of the damped system."""
        s, ys, vinvs = self.schur(lam)
        rhs = -self.gg.copy()
        for (idx, k), y in zip(self.groups, ys):
            rhs += y @ self.gl[idx, :k].ravel()
        try:
            dg = scipy.linalg.cho_solve(scipy.linalg.cho_factor(s), rhs)
        except np.linalg.LinAlgError:
            dg = np.linalg.lstsq(s, rhs, rcond=None)[0]
        back = -self.gl - (dg @ self.w).reshape(self.gl.shape)
        dl = np.zeros_like(self.gl)
        for (idx, k), vinv in zip(self.groups, vinvs):
            dl[idx, :k] = np.matmul(vinv, back[idx, :k, None])[:, :, 0]
        return dg, dl

    def predicted_reduction(self, dg, dl, lam) -> float:
        """``-(g^T dx + 0.5 dx^T J^T J dx)`` (the model's cost decrease, no damping)."""
        jtj_dx_g = self.u @ dg + self.w @ dl.ravel()
        jtj_dx_l = (dg @ self.w).reshape(dl.shape) + np.matmul(self.v, dl[:, :, None])[:, :, 0]
        jtj_dx_l = np.where(self.padded, 0.0, jtj_dx_l)
        grad = dg @ self.gg + (dl * self.gl).sum()
        quad = dg @ jtj_dx_g + (dl * jtj_dx_l).sum()
        return float(-(grad + 0.5 * quad))


def solve_lm(
    problem: Problem,
    x0: Float[np.ndarray, " X"],
    blocks: BlockStructure,
    *,
    loss: str = "linear",
    f_scale: float = 1.0,
    max_nfev: int | None = None,
    ftol: float = 1e-6,
    xtol: float = 1e-10,
    gtol: float = 1e-10,
    max_iter: int = 100,
    **unused,
) -> OptimizeResult:
    """Minimize ``problem``'s (robust) cost from ``x0`` (:meth:`Problem.pack`) by
    Levenberg-Marquardt; ``loss`` and ``f_scale`` as ``scipy.optimize.least_squares``, ``max_nfev``
    default ``max_iter + 1``. The result has scipy's ``x``, ``cost``, ``fun``, ``nfev``, ``njev``,
    ``status``, ``message`` and ``success``. It stops when an accepted step lowers the cost by less
    than ``ftol`` relatively (tighter than ``1e-6`` only creeps on), moves ``x`` by less than
    ``xtol`` relatively, or the scaled gradient is below ``gtol``. The damped step wanders along a
    gauge: hold it fixed."""
    if unused:
        log.debug("Levenberg-Marquardt ignores %s", sorted(unused))
    max_nfev = max_iter + 1 if max_nfev is None else int(max_nfev)
    gcols = blocks.global_cols
    bcols = blocks.block_cols
    local_mask = bcols >= 0

    def evaluate(x):
        raw = problem.residuals(x)
        rho, _ = _loss(loss, (raw / f_scale) ** 2)
        return raw, 0.5 * f_scale**2 * rho.sum()

    x = np.asarray(x0, float).copy()
    raw, cost = evaluate(x)
    nfev, njev, lam, nu = 1, 0, 1e-3, 2.0
    status, message = 0, "the maximum number of function evaluations is exceeded"
    system = None
    while nfev < max_nfev:
        jac = problem.jacobian(x)
        njev += 1
        _, drho = _loss(loss, (raw / f_scale) ** 2)
        scale = np.sqrt(drho)
        system = ReducedSystem(scipy.sparse.diags(scale) @ jac, scale * raw, blocks)
        gnorm = max(
            np.abs(system.gg).max(initial=0) / np.sqrt(system.diag_u.max()),
            np.abs(system.gl).max(initial=0) / np.sqrt(system.diag_v.max()),
        )
        if gnorm < gtol * max(1.0, np.sqrt(2 * cost)):
            status, message = 1, "`gtol` termination condition is satisfied."
            break
        accepted = False
        while nfev < max_nfev:
            dg, dl = system.step(lam)
            dx = np.zeros_like(x)
            dx[gcols] = dg
            dx[bcols[local_mask]] = dl[local_mask]
            x_new = x + dx
            raw_new, cost_new = evaluate(x_new)
            nfev += 1
            predicted = system.predicted_reduction(dg, dl, lam)
            actual = cost - cost_new
            rho = actual / predicted if predicted > 0 else -1.0
            log.debug(
                "LM nfev %d cost %.6g -> %.6g (rho %.3g, lambda %.3g)",
                nfev,
                cost,
                cost_new,
                rho,
                lam,
            )
            if np.isfinite(cost_new) and rho > 0:
                # shrink fast: a long-focal rig's weak directions move only at a tiny lambda
                lam = max(lam * (0.1 if rho > 0.75 else max(1 / 3, 1 - (2 * rho - 1) ** 3)), 1e-15)
                nu = 2.0
                small_step = np.linalg.norm(dx) <= xtol * (xtol + np.linalg.norm(x))
                small_cost = actual <= ftol * cost
                x, raw, cost = x_new, raw_new, cost_new
                accepted = True
                if small_cost:
                    status, message = 2, "`ftol` termination condition is satisfied."
                elif small_step:
                    status, message = 3, "`xtol` termination condition is satisfied."
                break
            lam *= nu
            nu *= 2
            if lam > 1e16:
                break
        if status or not accepted:
            if not accepted and not status:
                status, message = 2, "no further decrease (damping at its limit)"
            break
    return OptimizeResult(
        x=x,
        cost=float(cost),
        fun=raw,
        nfev=nfev,
        njev=njev,
        status=status,
        message=message,
        success=status > 0,
    )


def weak_directions(
    hessian: Float[np.ndarray, "G G"], n_gauge: int
) -> tuple[float, int, Float[np.ndarray, " G"]]:
    """How well the reduced Hessian, scaled to unit diagonal (units do not matter), pins its
    unknowns beyond the gauge: ``(ratio, count, direction)``, its ``n_gauge``-th smallest eigenvalue
    (the weakest non-gauge direction) over its largest, how many eigenvalues beyond the gauge lie
    below ``1e-9`` of the largest, and that weakest direction ``(G,)`` (unit, in the scaled
    unknowns; empty when there is none)."""
    d = np.sqrt(np.maximum(np.diag(hessian), 1e-300))
    eig, vec = np.linalg.eigh(hessian / d[:, None] / d[None, :])
    eig = np.maximum(eig, 0.0)
    if eig.size <= n_gauge:
        return float("inf"), 0, np.zeros(0)
    ratio = float(eig[n_gauge] / eig[-1])
    return ratio, int((eig[n_gauge:] < 1e-9 * eig[-1]).sum()), vec[:, n_gauge]
