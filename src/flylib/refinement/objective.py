"""The spatiotemporal objective: its terms, their normal equations, and the band layout.

Unknowns are every point of every frame of a chunk, ``X (T, P, 3)``. The objective is

.. math::

    F(X) = \\sum_{v,t,p} w_{vtp}\\, \\rho\\big(|\\pi_v(X_{tp}) - x_{vtp}|^2 / s^2\\big)
         + \\lambda_s \\sum_{t,p} |\\Delta^d X_{tp}|^2 / s_s^2
         + \\lambda_b \\sum_{t,b} (|X_{t i_b} - X_{t j_b}| - L_b)^2 / s_b^2
         + \\lambda_r \\sum_{t, p \\in R} |X_{tp} - C_p|^2 / s_r^2

(robust reprojection with scale ``s`` px and confidence weights ``w``; ``d``-th temporal
differences; one length ``L_b`` per bone; rigid points held at one world position ``C_p`` for the
recording). Every term is dimensionless, so the weights ``lambda`` compare like with like.

The reprojection term's Gauss-Newton blocks come from one jitted JAX kernel: forward-mode
derivatives of the projection model of :func:`flylib.camera.jax_model.project_full_one` (the one
bundle adjustment uses), with the robust loss applied as iteratively reweighted least squares.
The other terms are quadratic or rank-one.

Band layout: the points are packed into *blocks* of at most ``m`` points (whole limb chains, so
that every bone stays inside a block) and the unknowns ordered ``(block, frame, slot, xyz)``.
Within a frame a block couples ``3m`` unknowns; the temporal term couples the same unknown ``d``
frames apart, ``3m d`` positions away. The normal matrix is therefore banded with half-bandwidth
``3 m d`` (15 for the fly's legs with first differences) and is factorized by LAPACK's banded
Cholesky (``scipy.linalg.cholesky_banded``) in time linear in the number of frames."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING

import numpy as np

from ..camera import model as camera_model

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float, Int

LOSSES = ("linear", "huber", "soft_l1", "cauchy")


def _loss_jax(z, loss: str):
    """``(rho(z), rho'(z))`` in JAX."""
    import jax.numpy as jnp

    if loss == "linear":
        return z, jnp.ones_like(z)
    if loss == "soft_l1":
        root = jnp.sqrt(1.0 + z)
        return 2.0 * (root - 1.0), 1.0 / root
    if loss == "huber":
        small = z <= 1.0
        root = jnp.sqrt(jnp.maximum(z, 1.0))
        return jnp.where(small, z, 2.0 * root - 1.0), jnp.where(small, 1.0, 1.0 / root)
    if loss == "cauchy":
        return jnp.log1p(z), 1.0 / (1.0 + z)
    raise ValueError(f"unknown loss {loss!r} (known: {', '.join(LOSSES)})")


@cache
def chunk_kernel(loss: str, order: int, m: int):
    """The jitted evaluation of one chunk: cost, banded normal matrix and gradient.

    ``evaluate(xs, data) -> (cost, rows, grad, err)`` with ``xs`` ``(n_blocks, T, m, 3)`` the
    slotted points and ``data`` a dict of dense arrays (no scatter: every sum is over a padded
    axis):

    - observations on a grid ``(n_blocks, m, W)`` of (slot, view) cells, ``W`` the most views any
      point is seen from: ``rmat`` ``(..., 3, 3)``, ``tvec`` ``(..., 3)``, ``intr`` ``(..., 4)``,
      ``dist`` ``(..., D)``, ``xy`` ``(2, n_blocks, m, W, T)``, ``w`` ``(..., T)`` (0 = unused),
      ``inv_s2`` (1 / scale_px^2);
    - bones as ``incidence`` rows ``(n_blocks, Kb, m)`` (+1 / -1 at the bone's two slots, zero
      rows for padding), ``length`` ``(n_blocks, Kb)``, ``bone_w``;
    - rigid points ``rigid_mask`` ``(n_blocks, m)``, ``centre`` ``(n_blocks, m, 3)``, ``rigid_w``;
    - temporal ``gram`` ``(order + 1, T)`` (:func:`difference_gram` of the live frames, zero over
      the padding), ``smooth_w``;
    - ``live`` ``(T,)``: 1 for the chunk's frames, 0 for the padding that rounds ``T`` up to a
      compiled shape (no term reaches a padded frame).

    ``cost`` ``(n_blocks,)`` is the objective per block (the blocks share no unknown); ``rows``
    ``(6, n)`` the within-frame part of the Gauss-Newton matrix (IRLS weights for the robust
    loss), row ``delta`` its ``delta``-th superdiagonal at the column of the lower-right end
    (:func:`assemble_band` adds :func:`temporal_band`'s rows and makes LAPACK's band); ``grad``
    ``(n,)`` the gradient (both halved: the step solves ``A d = -grad``); ``err`` ``(n_blocks, m,
    W, T)`` pixel errors."""
    import jax
    import jax.numpy as jnp

    from ..camera import jax_model  # noqa: F401  (float64, CPU, compile cache)

    band_width(m, order)

    def evaluate(xs, data):
        # T-last layouts throughout: every elementwise op runs along frames
        xk = jnp.transpose(xs, (0, 2, 3, 1))  # (nb, m, 3, T)
        h, g, cost, sq = _reprojection_terms(xk, data, loss)
        h, g, cost = _rigid_terms(h, g, cost, xk, data)
        diag, nxt, g, cost = _bone_terms(h, g, cost, xk, data, m)
        diag = jnp.transpose(diag, (0, 4, 1, 2, 3))  # (nb, T, m, 3, 3)
        nxt = jnp.transpose(nxt, (0, 4, 1, 2, 3))  # (nb, T, m - 1, 3, 3)
        g = jnp.transpose(g, (0, 3, 1, 2))  # (nb, T, m, 3)
        if order:
            g, cost = _temporal_terms(g, cost, xs, data, order)
        rows = _band_rows(diag, nxt, m)
        err = jnp.sqrt(sq)  # (nb, m, W, T)
        return cost, jnp.stack(rows), g.reshape(-1), err

    return jax.jit(evaluate)


# The kernel's terms, traced inside chunk_kernel's evaluate in this order (the jitted
# computation is the same as one function's).


def _pixel(pc, intr, dist):
    """Camera frame -> pixels, the model of jax_model.project_full_one, elementwise."""
    # components as sequences (pc 3, intr 4, dist 12) of same-shaped arrays, so that
    # no op stacks or transposes the large (nb, m, W, T) arrays
    x, y = pc[0] / pc[2], pc[1] / pc[2]
    if dist is not None:
        radial, add_x, add_y = camera_model.distortion_terms(x, y, dist)
        x, y = x * radial + add_x, y * radial + add_y
    return intr[0] * x + intr[2], intr[1] * y + intr[3]


def _reprojection_terms(xk, data, loss: str):
    """The robust reprojection term summed over the views: Gauss-Newton blocks ``h`` ``(nb, m,
    3, 3, T)``, gradient ``g`` ``(nb, m, 3, T)``, cost per block ``(nb,)`` and the squared pixel
    errors ``(nb, m, W, T)``."""
    import jax
    import jax.numpy as jnp

    rmat, tvec = data["rmat"], data["tvec"]  # (nb, m, W, 3, 3), (nb, m, W, 3)
    r = [[rmat[..., i, j, None] for j in range(3)] for i in range(3)]  # each (nb, m, W, 1)
    xw = [xk[:, :, None, j] for j in range(3)]  # each (nb, m, 1, T)
    pc = tuple(
        r[i][0] * xw[0] + r[i][1] * xw[1] + r[i][2] * xw[2] + tvec[..., i, None] for i in range(3)
    )
    intr = [data["intr"][..., k, None] for k in range(4)]
    dist = data.get("dist")
    dist = None if dist is None else [dist[..., k, None] for k in range(dist.shape[-1])]
    proj = _pixel(pc, intr, dist)  # 2 x (nb, m, W, T)
    # d pixel / d world point: one JVP per camera-frame axis (through the same
    # model), chained with the rotation
    units = [tuple(jnp.full_like(c, float(k == i)) for k, c in enumerate(pc)) for i in range(3)]
    dpix = [jax.jvp(lambda *p: _pixel(p, intr, dist), pc, units[i])[1] for i in range(3)]
    jac = [
        [dpix[0][a] * r[0][j] + dpix[1][a] * r[1][j] + dpix[2][a] * r[2][j] for j in range(3)]
        for a in range(2)
    ]  # jac[a][j] (nb, m, W, T)
    xy = data["xy"]  # (2, nb, m, W, T)
    e = (proj[0] - xy[0], proj[1] - xy[1])
    sq = e[0] * e[0] + e[1] * e[1]
    rho, drho = _loss_jax(sq * data["inv_s2"], loss)
    w = data["w"]
    scale = w * drho * data["inv_s2"]
    # the 6 Gauss-Newton entries, 3 gradient entries and the cost summed over the W views by ONE
    # variadic reduction: XLA computes every summand in a single pass over the (nb, m, W, T)
    # cells instead of materialising the Jacobian
    sj = [[scale * jac[a][i] for i in range(3)] for a in range(2)]  # each (nb, m, W, T)
    pairs = [(i, j) for i in range(3) for j in range(i, 3)]
    summands = (
        [sj[0][i] * jac[0][j] + sj[1][i] * jac[1][j] for i, j in pairs]
        + [sj[0][i] * e[0] + sj[1][i] * e[1] for i in range(3)]
        + [w * rho]
    )
    sums = jax.lax.reduce(
        tuple(summands),
        (0.0,) * len(summands),
        lambda a, b: tuple(x + y for x, y in zip(a, b)),
        (2,),
    )  # each (nb, m, T)
    entry = {}
    for (i, j), value in zip(pairs, sums):
        entry[i, j] = entry[j, i] = value
    h = jnp.stack(
        [jnp.stack([entry[i, j] for j in range(3)]) for i in range(3)]
    )  # (3, 3, nb, m, T)
    g = jnp.stack(sums[len(pairs) : len(pairs) + 3])  # (3, nb, m, T)
    # per block: blocks share no unknown, so the solver accepts or rejects a step block by block
    cost = jnp.sum(sums[-1], axis=(1, 2))
    h = jnp.transpose(h, (2, 3, 0, 1, 4))  # (nb, m, 3, 3, T)
    g = jnp.transpose(g, (1, 2, 0, 3))  # (nb, m, 3, T)
    return h, g, cost, sq


def _rigid_terms(h, g, cost, xk, data):
    """Rigid points: one world position each; ``h``, ``g``, ``cost`` with the term added."""
    import jax.numpy as jnp

    # padded frames (live 0) carry no term: their unknowns stay where they are
    live = data["live"]  # (T,)
    mask = data["rigid_mask"][:, :, None, None] * live  # (nb, m, 1, T)
    diff = (xk - data["centre"][..., None]) * mask  # (nb, m, 3, T)
    g = g + data["rigid_w"] * diff
    h = h + data["rigid_w"] * jnp.eye(3)[None, None, :, :, None] * mask[:, :, :, None]
    cost += data["rigid_w"] * jnp.sum(diff * diff, axis=(1, 2, 3))
    return h, g, cost


def _bone_terms(h, g, cost, xk, data, m: int):
    """Bones: within-frame blocks on the diagonal (slot k, k) and next to it (k, k+1); ``(diag
    (nb, m, 3, 3, T), nxt (nb, m - 1, 3, 3, T), g, cost)``."""
    import jax.numpy as jnp

    nb, n_frames = xk.shape[0], xk.shape[3]
    live = data["live"]  # (T,)
    # a bone joins neighbouring slots (chains are packed contiguously). Loops over the few bones
    # per block instead of einsums: XLA's contractions over these tiny axes are slow.
    inc = data["incidence"]  # (nb, Kb, m)
    n_bones = inc.shape[1]
    d = jnp.sum(inc[:, :, :, None, None] * xk[:, None], axis=2)  # (nb, Kb, 3, T)
    length = jnp.maximum(jnp.sqrt(jnp.sum(d * d, axis=2)), 1e-12)  # (nb, Kb, T)
    unit = d / length[:, :, None]
    target = data["length"][..., None]
    resid = (length - target) * (target > 0) * live
    grad_b = data["bone_w"] * resid[:, :, None] * unit  # (nb, Kb, 3, T)
    diag = h
    nxt = jnp.zeros((nb, max(m - 1, 1), 3, 3, n_frames))
    for q in range(n_bones):
        outer = data["bone_w"] * live * unit[:, q, :, None] * unit[:, q, None, :]  # (nb, 3, 3, T)
        # slot k gets +outer for each bone touching it, (k, k+1) gets -outer
        diag = diag + jnp.abs(inc[:, q])[:, :, None, None, None] * outer[:, None]
        if m > 1:
            link = -inc[:, q, :-1] * inc[:, q, 1:]  # 1 where bone q joins slots k, k+1
            nxt = nxt - link[:, :, None, None, None] * outer[:, None]
        g = g + inc[:, q][:, :, None, None] * grad_b[:, q, None]
    cost += data["bone_w"] * jnp.sum(resid * resid, axis=(1, 2))
    return diag, nxt, g, cost


def _temporal_terms(g, cost, xs, data, order: int):
    """Temporal differences of order ``order``: ``g`` ``(nb, T, m, 3)``, ``cost`` with the term."""
    import jax.numpy as jnp

    gram = data["gram"]
    live = data["live"]  # (T,)
    sw = data["smooth_w"]
    dx = jnp.diff(xs, n=order, axis=1) * live[order:, None, None]
    cost += sw * jnp.sum(dx * dx, axis=(1, 2, 3))
    smooth = gram[0][None, :, None, None] * xs
    zero = jnp.zeros_like(xs)
    for q in range(1, order + 1):
        c = gram[q][None, :, None, None]
        # (D^T D)[t - q, t] x[t - q] + (D^T D)[t, t + q] x[t + q]
        back = jnp.concatenate([zero[:, :q], xs[:, :-q]], axis=1) * c
        ahead = jnp.concatenate([(c * xs)[:, q:], zero[:, :q]], axis=1)
        smooth = smooth + back + ahead
    g = g + sw * smooth
    return g, cost


def _band_rows(diag, nxt, m: int) -> list:
    """The band's non-zero within-frame rows: the delta-th superdiagonals (delta < 6), as above."""
    import jax.numpy as jnp

    nb, n_frames = diag.shape[0], diag.shape[1]
    rows = []
    zero = jnp.zeros((nb, n_frames, m))
    for delta in range(min(6, 3 * m)):
        cols = []
        for jj in range(3):
            ii = jj - delta
            if ii >= 0:
                cols.append(diag[..., ii, jj])
            elif ii + 3 >= 0 and m > 1:
                cols.append(
                    jnp.concatenate([zero[..., :1], nxt[..., : m - 1, ii + 3, jj]], axis=-1)
                )
            else:
                cols.append(zero)
        rows.append(jnp.stack(cols, axis=-1).reshape(-1))
    return rows


@dataclass(frozen=True)
class BlockLayout:
    """Points packed into blocks of ``m`` slots (whole limb chains per block): ``slots`` the
    point index of each slot (``-1``: empty), ``block_of`` and ``slot_of`` those of every point."""

    slots: Int[np.ndarray, "n_blocks m"]
    block_of: Int[np.ndarray, " P"]
    slot_of: Int[np.ndarray, " P"]

    @property
    def m(self) -> int:
        return int(self.slots.shape[1])

    @property
    def n_blocks(self) -> int:
        return int(self.slots.shape[0])

    @classmethod
    def from_chains(cls, n_points: int, chains: list[list[int]]) -> BlockLayout:
        """First-fit packing of the (disjoint) ``chains``, longest first, then the loose points."""
        chains = [list(c) for c in chains if c]
        seen = {p for c in chains for p in c}
        chains += [[p] for p in range(n_points) if p not in seen]
        m = max((len(c) for c in chains), default=1)
        blocks: list[list[int]] = []
        for chain in sorted(chains, key=len, reverse=True):
            for block in blocks:
                if len(block) + len(chain) <= m:
                    block.extend(chain)
                    break
            else:
                blocks.append(list(chain))
        slots = np.full((len(blocks), m), -1, dtype=np.int64)
        block_of = np.zeros(n_points, dtype=np.int64)
        slot_of = np.zeros(n_points, dtype=np.int64)
        for b, block in enumerate(blocks):
            slots[b, : len(block)] = block
            block_of[block] = b
            slot_of[block] = np.arange(len(block))
        return cls(slots, block_of, slot_of)


def difference_gram(n_frames: int, order: int) -> Float[np.ndarray, "order_1 T"]:
    """Diagonals of ``D^T D`` for the ``order``-th difference operator on ``n_frames``: row ``q``
    holds ``(D^T D)[t - q, t]`` at column ``t`` (zero for ``t < q``)."""
    out = np.zeros((order + 1, n_frames))
    if order == 0 or n_frames <= order:
        return out
    coef = np.array([1.0])
    for _ in range(order):
        coef = np.convolve(coef, [1.0, -1.0])
    rows = n_frames - order
    for q in range(order + 1):
        for a in range(order + 1 - q):
            # difference rows k = 0..rows-1 add coef[a] coef[a+q] at column k + a + q
            out[q, a + q : a + q + rows] += coef[a] * coef[a + q]
    return out


def temporal_band(
    layout: BlockLayout,
    order: int,
    gram: Float[np.ndarray, "order_1 T"],
    smooth_w: float,
    live: Float[np.ndarray, " T"] | None = None,
) -> Float[np.ndarray, "order_1 n"]:
    """The constant part of the normal matrix: the temporal term on real slots, and a unit
    diagonal for empty slots and padded frames (``live`` 0), whose unknowns then never move. Row
    ``q`` is the ``3 m q``-th superdiagonal (row 0 the diagonal), at the column of its lower-right
    end, i.e. band row ``u - 3 m q`` of LAPACK's upper storage (:func:`assemble_band`)."""
    m = layout.m
    width = 3 * m
    n_blocks = layout.n_blocks
    n_frames = gram.shape[1]
    real = np.repeat((layout.slots >= 0).astype(float), 3, axis=1)[:, None, :]  # (nb, 1, 3m)
    if live is not None:
        real = real * np.asarray(live, float)[None, :, None]  # (nb, T, 3m)
    out = np.zeros((order + 1, n_blocks * n_frames * width))
    if order and smooth_w:
        for q in range(order + 1):
            out[q] = (smooth_w * gram[q][None, :, None] * real).ravel()
    out[0] += np.broadcast_to(1.0 - real, (n_blocks, n_frames, width)).ravel()
    return out


def assemble_band(
    rows: Float[np.ndarray, "k n"],
    temporal: Float[np.ndarray, "order_1 n"],
    width: int,
    u: int,
    columns: Bool[np.ndarray, " n"] | None = None,
    mu: Float[np.ndarray, " n"] | float = 0.0,
    floor: float = 0.0,
    buffer: Float[np.ndarray, "n u_1"] | None = None,
) -> Float[np.ndarray, "u_1 n_columns"]:
    """The (damped) normal matrix in LAPACK's upper band storage, Fortran-ordered (what
    ``cholesky_banded(..., overwrite_ab=True)`` factorizes in place): ``(u + 1, n_columns)``,
    entry ``(u + i - j, j)`` is ``A[i, j]`` for ``i <= j``.

    ``rows``: :func:`chunk_kernel`'s within-frame superdiagonals ``0 .. k - 1``; ``width`` is
    ``3 m``, ``u`` the half-bandwidth (:func:`band_width`); ``columns`` ``(n,)`` bool: only these
    unknowns (whole blocks, which share nothing; None: all); damping makes the diagonal ``diag *
    (1 + mu) + floor`` (``mu`` scalar or ``(n,)``); ``buffer`` ``(n, u + 1)`` C-ordered float64 to
    build the band in (the result is a view of it): reusing one spares the page faults of a fresh
    allocation at every step."""
    if columns is not None:
        rows, temporal = rows[:, columns], temporal[:, columns]
        if not np.isscalar(mu):
            mu = mu[columns]
    k = rows.shape[0]
    # built transposed (C-ordered (n, u + 1): each unknown's band column contiguous) and returned
    # as its Fortran-ordered view; the kernel's rows land in one block of adjacent entries
    if buffer is None:
        out = np.zeros((rows.shape[1], u + 1))
    else:
        out = buffer[: rows.shape[1]]
        out[:, : u - k + 1] = 0.0
    out[:, u - k + 1 :] = rows[::-1].T
    out[:, u] = (rows[0] + temporal[0]) * (1.0 + mu) + floor
    for q in range(1, temporal.shape[0]):
        out[:, u - q * width] += temporal[q]
    return out.T


def band_width(m: int, order: int) -> int:
    """Half-bandwidth ``u`` of the normal matrix for blocks of ``m`` points."""
    return max(3 * m - 1, 3 * m * order)


def to_slots(
    per_point: Float[np.ndarray, "T P *rest"], slots: Int[np.ndarray, "n_blocks m"]
) -> Float[np.ndarray, "n_blocks T m *rest"]:
    """``(T, P, ...)`` -> ``(n_blocks, T, m, ...)`` (zeros in empty slots)."""
    pad = np.zeros((per_point.shape[0], 1, *per_point.shape[2:]))
    padded = np.concatenate([per_point, pad], axis=1)
    index = np.where(slots >= 0, slots, per_point.shape[1])
    return np.moveaxis(padded[:, index], 0, 1)


def from_slots(
    slotted: Float[np.ndarray, "n_blocks T m *rest"],
    slots: Int[np.ndarray, "n_blocks m"],
    n_points: int,
) -> Float[np.ndarray, "T P *rest"]:
    """``(n_blocks, T, m, ...)`` -> ``(T, P, ...)``."""
    ok = slots >= 0
    out = np.zeros((slotted.shape[1], n_points, *slotted.shape[3:]))
    out[:, slots[ok]] = np.moveaxis(slotted, 1, 0)[:, ok]
    return out
