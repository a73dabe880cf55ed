"""Inverse kinematics on NeuroMechFly's leg chains (JAX, float64, CPU).

Each (frame, leg) is one small least-squares problem: the seven angles of
:data:`~flylib.neuromechfly.model.DOF_SUFFIXES` that put the model's coxa-trochanter, femur-tibia,
tibia-tarsus and claw (forward kinematics from the model's thorax-coxa joint) nearest the aligned
measured points. All problems are solved at once (``vmap``) by Levenberg-Marquardt with a
forward-mode Jacobian, started from the closed-form angles of straight segments
(:func:`initial_angles`), which also picks the model's branch among the chain's mirror-twin
solutions (a thorax-coxa yaw/pitch/roll and its ``(yaw + pi, pi - pitch, roll + pi)`` twin place
the leg identically). Unlike SeqIKPy's stage-by-stage fits of growing sub-chains, all seven
angles are fitted together against all four points."""

from __future__ import annotations

from functools import cache
from typing import TYPE_CHECKING

import numpy as np

from ..camera import jax_model  # noqa: F401  (float64 and the CPU for JAX, before jax is used)
from ..config.neuromechfly import NeuromechflyParams
from .model import LEGS, leg_forward, rotations, segment_offsets, thorax_coxa_template

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

ITERATIONS = NeuromechflyParams.iterations
CHUNK_FRAMES = 2048


def _unit(v: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def initial_angles(root: Float[np.ndarray, " 3"], points: Float[np.ndarray, "N 4 3"]) -> np.ndarray:
    """Closed-form angles ``(N, 7)`` (radians, flygym's order) of a leg whose segments lie on
    their local -z axes: each segment direction, seen in its parent's frame, gives one or two
    angles. The model's segments are within 0.5 degrees of that, so the fit starts in the right
    basin; the branch is the model's range (coxa-trochanter pitch <= 0, femur-tibia pitch >= 0)."""
    chain = np.concatenate([np.broadcast_to(root, points[:, :1].shape), points], axis=1)
    d = _unit(np.diff(chain, axis=1))  # (N, 4, 3) segment directions, thorax frame
    pitch = np.arcsin(np.clip(-d[:, 0, 0], -1, 1))
    yaw = np.arctan2(d[:, 0, 1], -d[:, 0, 2])
    frame = rotations(np, yaw, 0) @ rotations(np, pitch, 1)
    f = np.einsum("nji,nj->ni", frame, d[:, 1])
    ctr_pitch = -np.arccos(np.clip(-f[:, 2], -1, 1))
    roll = np.arctan2(f[:, 1], f[:, 0])
    frame = frame @ rotations(np, roll, 2) @ rotations(np, ctr_pitch, 1)
    g = np.einsum("nji,nj->ni", frame, d[:, 2])
    fti = np.arccos(np.clip(-g[:, 2], -1, 1))
    ctr_roll = np.arctan2(-g[:, 1], -g[:, 0])
    frame = frame @ rotations(np, ctr_roll, 2) @ rotations(np, fti, 1)
    h = np.einsum("nji,nj->ni", frame, d[:, 3])
    tita = np.arctan2(-h[:, 0], -h[:, 2])
    angles = np.stack([pitch, roll, yaw, ctr_pitch, ctr_roll, fti, tita], axis=-1)
    return np.nan_to_num(angles)


@cache
def _solver(iterations: int):
    import jax
    import jax.numpy as jnp

    def residual(theta, root, offsets, target):
        return (leg_forward(theta, root, offsets, xp=jnp)[1:] - target).ravel()

    jacobian = jax.jacfwd(residual)

    def solve_one(theta0, root, offsets, target):
        def cost(theta):
            r = residual(theta, root, offsets, target)
            return r @ r

        def step(_, state):
            theta, lam, current = state
            r = residual(theta, root, offsets, target)
            jac = jacobian(theta, root, offsets, target)
            jtj = jac.T @ jac
            damped = jtj + lam * jnp.diag(jnp.diag(jtj) + 1e-9)
            trial = theta - jnp.linalg.solve(damped, jac.T @ r)
            trial_cost = cost(trial)
            better = trial_cost < current
            return (
                jnp.where(better, trial, theta),
                jnp.where(better, lam * 0.3, lam * 10.0),
                jnp.where(better, trial_cost, current),
            )

        theta, _, final = jax.lax.fori_loop(
            0, iterations, step, (theta0, jnp.asarray(1e-3), cost(theta0))
        )
        return theta, final

    return jax.jit(jax.vmap(solve_one, in_axes=(0, None, None, 0)))


def solve_leg_angles(
    aligned: Float[np.ndarray, "T 6 5 3"],
    *,
    offsets: Float[np.ndarray, "6 4 3"] | None = None,
    iterations: int = ITERATIONS,
) -> Float[np.ndarray, "T 6 7"]:
    """Each leg's seven joint angles (radians in ``(-pi, pi]``, flygym's order) for ``aligned``
    legs (mm, :func:`~flylib.neuromechfly.align.align_to_template`; the thorax-coxa row is not
    fitted: the chain's root is the model's); NaN for a (frame, leg) missing any of its four
    distal points. ``offsets``: the chains' segment offsets, default the model's."""
    aligned = np.asarray(aligned, dtype=np.float64)
    n_frames = aligned.shape[0]
    out = np.full((n_frames, len(LEGS), 7), np.nan)
    complete = np.isfinite(aligned[:, :, 1:]).all(axis=(2, 3))
    roots = thorax_coxa_template()
    offsets = segment_offsets() if offsets is None else np.asarray(offsets, dtype=np.float64)
    solve = _solver(int(iterations))
    for k in range(len(LEGS)):
        frames = np.flatnonzero(complete[:, k])
        for begin in range(0, frames.size, CHUNK_FRAMES):
            chunk = frames[begin : begin + CHUNK_FRAMES]
            # pad to a fixed size: one compiled shape for every chunk
            padded = np.resize(chunk, CHUNK_FRAMES) if chunk.size < CHUNK_FRAMES else chunk
            targets = aligned[padded, k, 1:]
            start = initial_angles(roots[k], targets)
            thetas, _ = solve(start, roots[k], offsets[k], targets)
            out[chunk, k] = np.asarray(thetas)[: chunk.size]
    return np.mod(out + np.pi, 2 * np.pi) - np.pi
