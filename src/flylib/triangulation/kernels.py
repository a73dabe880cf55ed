"""The jitted JAX kernel of greedy triangulation, over one chunk of points.

Separate from :mod:`flylib.triangulation.methods` so that RANSAC (NumPy) and the rest of a
workflow job never import JAX; ``greedy`` imports it when called (the DLT kernel is
:func:`flylib.camera.jax_model.dlt_chunk`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from ..camera import jax_model

if TYPE_CHECKING:  # pragma: no cover
    from jax import Array
    from jaxtyping import Bool, Float


# Over one chunk: raw / und (V, N, 2), weights (V, N). Arrays are component-major with the
# point axis last, so XLA fuses each kernel into vectorized loops over points.


def _view_sq_error(rig, k, x, y, z, raw_u, raw_v, distorted):
    """Squared pixel error in view ``k`` of points ``(x, y, z)`` against ``raw_u/v``."""
    if distorted:
        r, t = rig["rmats"][k], rig["tvecs"][k]
        cx_ = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
        cy_ = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
        cz_ = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
        intr = rig["intrs"][k]
        u, v = jax_model.pixels_from_normalized(
            cx_ / cz_, cy_ / cz_, intr[0], intr[1], intr[2], intr[3], rig["dists"][k]
        )
    else:
        p = rig["pmats"][k]
        inv_depth = 1.0 / (p[2, 0] * x + p[2, 1] * y + p[2, 2] * z + p[2, 3])
        u = (p[0, 0] * x + p[0, 1] * y + p[0, 2] * z + p[0, 3]) * inv_depth
        v = (p[1, 0] * x + p[1, 1] * y + p[1, 2] * z + p[1, 3]) * inv_depth
    du, dv = u - raw_u, v - raw_v
    return du * du + dv * dv


def _view_terms(rig, und, weights):
    """Per-view normal-equation terms ``(9, V, N)`` and the valid mask ``(V, N)``."""
    feats, valid = jax_model.dlt_features(jnp, und, rig["norm"], weights)  # (6, V, N)
    quad = rig["quad"]  # (V, 6, 9)
    terms = sum(feats[f][None] * quad[:, f, :].T[:, :, None] for f in range(6))
    return terms, valid


def _solve_kept(terms, kept, min_views=2):
    summed = (terms * kept[None]).sum(axis=1)  # (9, N)
    return jax_model.dlt_solve_terms(jnp, summed, kept.sum(axis=0), min_views)


@jax.jit
def greedy_chunk(
    rig: dict[str, Array],
    raw: Float[Array, "V N 2"],
    und: Float[Array, "V N 2"] | None,
    weights: Float[Array, "V N"] | None,
    threshold: float,
    max_drops: int,
) -> tuple[Float[Array, "N 3"], Bool[Array, "V N"]]:
    """Greedy view dropping on one chunk -> ``(pts3d, kept)``; ``und`` is None when the rig
    has no distortion."""
    distorted = und is not None  # the caller undistorts exactly when the rig has distortion
    und = raw if und is None else und
    terms, kept = _view_terms(rig, und, weights)
    n_views = kept.shape[0]

    def drop_worst(_, state):
        pts3d, kept = state
        x, y, z = pts3d[:, 0], pts3d[:, 1], pts3d[:, 2]
        err_sq = jnp.stack(
            [
                _view_sq_error(rig, k, x, y, z, raw[k, :, 0], raw[k, :, 1], distorted)
                for k in range(n_views)
            ]
        )
        err_sq = jnp.where(kept & jnp.isfinite(err_sq), err_sq, -jnp.inf)
        worst = jnp.argmax(err_sq, axis=0)
        offending = jnp.max(err_sq, axis=0) > threshold * threshold
        drop = (jnp.arange(n_views)[:, None] == worst[None, :]) & offending[None, :]
        kept = kept & ~drop
        return _solve_kept(terms, kept), kept

    pts3d, kept = jax.lax.fori_loop(0, max_drops, drop_worst, (_solve_kept(terms, kept), kept))
    accepted = jnp.isfinite(pts3d).all(axis=-1)
    return pts3d, kept & accepted[None]
