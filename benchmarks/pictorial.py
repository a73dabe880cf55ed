"""Pictorial-structures throughput: frames/s for K = 5 candidates, 7 views, 38 points.

Candidates per (view, point): the true peak (1 px noise), the mirrored joint's peak,
and three random peaks. Prints frames/s of the PS solve (hypotheses + chain DP, the
bone prior precomputed), with and without the temporal term, and the same-run
baseline of RANSAC triangulation of the arg-max peaks. Target: >= 200 frames/s.

Run: ``.venv/bin/python benchmarks/pictorial.py``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from flylib import pictorial as ps  # noqa: E402
from flylib.skeleton import Skeleton  # noqa: E402
from flylib.triangulation import reconstruct  # noqa: E402

from synthetic import default_rig, observe, project_opencv, synthetic_fly  # noqa: E402

N_FRAMES, K, TARGET_FPS = 400, 5, 200.0


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    rig, skeleton = default_rig(), Skeleton.fly()
    truth = synthetic_fly(N_FRAMES, seed=0)
    pts2d, conf = observe(truth, rig, noise_px=1.0, seed=0)
    mirrored = project_opencv(rig, truth[:, [(i + 19) % 38 for i in range(38)]])
    rng = np.random.default_rng(1)
    peaks = [pts2d, np.where(np.isfinite(pts2d), mirrored, np.nan)]
    peaks += [
        np.where(np.isfinite(pts2d), rng.random(pts2d.shape) * [960, 480], np.nan)
        for _ in range(K - 2)
    ]
    xy = np.stack(peaks, axis=3)
    score = np.stack([conf * f for f in np.linspace(1.0, 0.2, K)], axis=3)
    targets, scale = ps.solver.prior(rig, skeleton, pts2d, 100)
    chains = ps.skeleton_chains(skeleton)

    def timed(label, fn):
        fn()  # warm-up (JIT of the triangulation kernels, caches)
        t0 = time.perf_counter()
        fn()
        fps = N_FRAMES / (time.perf_counter() - t0)
        print(f"{label:<46s} {fps:8.1f} frames/s")
        return fps

    plain = timed(
        f"pictorial structures, K={K}",
        lambda: ps.solve_frames(rig, xy, score, chains, targets, scale=scale),
    )
    temporal = timed(
        f"pictorial structures, K={K}, temporal",
        lambda: ps.solve_frames(rig, xy, score, chains, targets, scale=scale, temporal=True),
    )
    full = timed(
        f"ps.reconstruct (prior + solve + DLT), K={K}",
        lambda: ps.reconstruct(rig, skeleton, ps.Candidates(xy, score)),
    )
    base = timed("baseline: RANSAC triangulation of arg-max", lambda: reconstruct(rig, pts2d))
    print(
        f"vs target {TARGET_FPS:.0f} frames/s: {plain / TARGET_FPS:.2f}x (temporal "
        f"{temporal / TARGET_FPS:.2f}x, reconstruct {full / TARGET_FPS:.2f}x); "
        f"RANSAC is {base / plain:.1f}x faster than PS"
    )


if __name__ == "__main__":
    main()
