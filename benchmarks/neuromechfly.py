"""NeuroMechFly leg angles: frames per second of ``compute_nmf_angles`` (alignment,
inverse kinematics of all six legs, forward-kinematics residual) on 10,000 frames.

Baselines measured in the same run, on the same aligned legs:

* ``scipy``: a per-(frame, leg) ``scipy.optimize.least_squares`` on the same chains
  (what solving the problems one at a time costs), on ``--baseline-frames`` frames;
* ``seqikpy``: SeqIKPy's ``LegInvKinSeq`` (stage-by-stage IKPy fits) on the two front
  legs (its packaged body config covers only those), on ``--baseline-frames`` frames,
  scaled to six legs; only where ``seqikpy`` imports (it pins ``pandas < 3``, so it
  lives in its own environment: ``PYTHONPATH=src <that env>/bin/python`` runs this file
  there when that environment also holds flylib's dependencies).

Run: ``.venv/bin/python benchmarks/neuromechfly.py [--frames 10000] [--baseline-frames 40]``
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np


def walking_angles(n_frames: int, seed: int = 0) -> np.ndarray:
    """``(T, 42)`` smooth leg angles around a standing pose (radians), 8 Hz steps."""
    rng = np.random.default_rng(seed)
    low = np.array([-0.3, -0.6, -0.3, -2.0, -0.6, 1.0, -1.0])
    high = np.array([0.6, 0.6, 0.3, -1.0, 0.6, 2.0, -0.3])
    base = rng.uniform(low, high, (6, 7)) * np.where(
        np.arange(6)[:, None] >= 3, [1, -1, -1, 1, -1, 1, 1], 1
    )
    t = np.arange(n_frames) / 100.0
    phase = rng.uniform(0, 2 * np.pi, (6, 7))
    swing = 0.25 * np.sin(2 * np.pi * 8.0 * t[:, None, None] + phase)
    return (base + swing).reshape(n_frames, 42)


def fly_points(angles: np.ndarray, seed: int = 0) -> tuple[np.ndarray, object]:
    """fly38 world points of the model's legs for ``angles`` (a rig-like world)."""
    from flylib.config import Config
    from flylib.neuromechfly.model import LEGS, forward_kinematics

    rng = np.random.default_rng(seed)
    skeleton = Config.default().skeleton()
    legs = forward_kinematics(angles) + rng.normal(0.0, 0.002, (angles.shape[0], 6, 5, 3))
    pts = np.zeros((angles.shape[0], len(skeleton.point_names), 3))
    for k, leg in enumerate(LEGS):
        index = [skeleton.point_names.index(p) for p in skeleton.limbs[f"{leg.lower()}_leg"]]
        pts[:, index] = legs[:, k]
    return 2.2 * pts + np.array([0.0, 0.0, 110.0]), skeleton


def scipy_baseline(aligned: np.ndarray, offsets: np.ndarray) -> float:
    """Seconds for per-(frame, leg) least squares on ``aligned`` ``(T, 6, 5, 3)``."""
    from scipy.optimize import least_squares

    from flylib.neuromechfly.ik import initial_angles
    from flylib.neuromechfly.model import leg_forward, thorax_coxa_template

    roots = thorax_coxa_template()
    start = time.perf_counter()
    for t in range(aligned.shape[0]):
        for k in range(6):
            target = aligned[t, k, 1:]
            x0 = initial_angles(roots[k], target[None])[0]
            least_squares(
                lambda a, k=k, target=target: (
                    leg_forward(a, roots[k], offsets[k])[1:] - target
                ).ravel(),
                x0,
                method="lm",
            )
    return time.perf_counter() - start


def seqikpy_baseline(aligned: np.ndarray) -> float | None:
    """Seconds for SeqIKPy on the two front legs of ``aligned``, or ``None``."""
    try:
        from seqikpy.body_config import neuromechfly_body_config as body
        from seqikpy.kinematic_chain import KinematicChainSeq
        from seqikpy.leg_inverse_kinematics import LegInvKinSeq
    except ImportError:
        return None
    legs = {"LF": 0, "RF": 3}
    size = {}
    for leg, k in legs.items():
        lengths = np.median(np.linalg.norm(np.diff(aligned[:, k], axis=1), axis=-1), axis=0)
        for name, length in zip(("Coxa", "Femur", "Tibia", "Tarsus"), lengths):
            size[f"{leg}_{name}"] = float(length)
        size[leg] = float(lengths.sum())
    solver = LegInvKinSeq(
        aligned_pos={f"{leg}_leg": aligned[:, k] for leg, k in legs.items()},
        kinematic_chain_class=KinematicChainSeq(
            bounds_dof=body.dof_bounds_rad, legs_list=list(legs), body_size=size
        ),
        initial_angles=body.initial_angles_rad,
    )
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        solver.run_ik_and_fk(hide_progress_bar=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--baseline-frames", type=int, default=40)
    args = parser.parse_args()

    from flylib.neuromechfly import compute_nmf_angles
    from flylib.neuromechfly.model import segment_offsets

    truth = walking_angles(args.frames)
    pts3d, skeleton = fly_points(truth)
    compute_nmf_angles(pts3d[:64], skeleton)  # compile once (one chunk shape)
    start = time.perf_counter()
    nmf = compute_nmf_angles(pts3d, skeleton)
    elapsed = time.perf_counter() - start
    error = np.degrees(np.abs(np.angle(np.exp(1j * (nmf.angles - truth)))))
    ours = args.frames / elapsed
    print(f"flylib   {args.frames:>6} frames x 6 legs: {elapsed:7.2f} s  {ours:9.1f} frames/s")
    print(
        f"         angle error vs truth (2 um noise): median {np.median(error):.3f} deg, "
        f"p99 {np.percentile(error, 99):.3f} deg; FK residual median "
        f"{np.nanmedian(nmf.residual):.4f} leg lengths"
    )

    subset = nmf.aligned[: args.baseline_frames]
    own = segment_offsets() * nmf.alignment.segment_scale[..., None]
    seconds = scipy_baseline(subset, own)
    rate = subset.shape[0] / seconds
    print(
        f"scipy    {subset.shape[0]:>6} frames x 6 legs: {seconds:7.2f} s  {rate:9.1f} frames/s"
        f"  (flylib {ours / rate:.0f}x)"
    )
    seconds = seqikpy_baseline(subset)
    if seconds is None:
        print("seqikpy  not importable here (it pins pandas < 3): no figure in this run")
    else:
        rate = subset.shape[0] / (3.0 * seconds)
        print(
            f"seqikpy  {subset.shape[0]:>6} frames x 2 legs: {seconds:7.2f} s  {rate:9.2f} "
            f"frames/s for 6 legs (x3 of 2)  (flylib {ours / rate:.0f}x)"
        )


if __name__ == "__main__":
    main()
