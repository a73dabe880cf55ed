"""Triangulation throughput on the default 7-camera rig (T = 10,000 frames x P = 38).

Prints frames/s for dlt, ransac and greedy, each warmed up first (dlt and greedy
are JAX kernels jitted once per chunk length; ransac is NumPy and compiles nothing:
the first-call column shows what a fresh process pays), and the speed-up over a
straightforward per-point loop (Hartley-normalized SVD DLT; for RANSAC that DLT over
every view pair) measured in the same run on a small subset. Two visibility patterns:

* ``all``: every point in all 7 views (the worst case for RANSAC: 21 pairs);
* ``plan``: what the default detection plan gives (each side's points in its 3
  side cameras plus the front camera), with 10% of detections missing.

The DLT is timed through both public call paths, ``flylib.triangulation.triangulate``
(``dlt``) and the seed API's ``CameraGroup.triangulate`` (``group``), which share one
chunked kernel, next to the unchunked NumPy DLT the seed-API method used to run
(``np-dlt``, ``camera_model.dlt_solve``), all in the same run.

Targets (2-core machine): dlt >= 100,000 frames/s, ransac >= 20,000 frames/s.

Run: ``.venv/bin/python benchmarks/triangulation.py [--frames 10000]``
"""

from __future__ import annotations

import argparse
import time
from itertools import combinations
from pathlib import Path

import numpy as np
import yaml

from flylib.camera import model as camera_model
from flylib.camera.rig import CameraGroup
from flylib.config.params import TriangulationParams
from flylib.triangulation import reconstruct, triangulate, triangulate_ransac

RIG_SPEC = Path(__file__).resolve().parents[2] / "shared" / "spec" / "fly38-rig.yaml"
N_POINTS = 38


class _Table:
    def __init__(self, cameras: dict):
        self._cameras = dict(cameras)

    def camera_table(self):
        cams = dict(self._cameras)
        return cams.pop("defaults", {}), cams


def default_rig() -> CameraGroup:
    if RIG_SPEC.is_file():
        cams = yaml.safe_load(RIG_SPEC.read_text())["cameras"]
    else:  # the same numbers, for a checkout without ../shared
        cams = {
            "defaults": {"focal_length_px": 22388.125, "distance": 107.463},
            **{
                n: {"azimuth_deg": a}
                for n, a in zip(
                    ["rh", "rm", "rf", "f", "lf", "lm", "lh"], [-120, -90, -45, 0, 45, 90, 120]
                )
            },
        }
    names = [n for n in cams if n != "defaults"]
    return CameraGroup.from_config(_Table(cams), image_sizes={n: (480, 960) for n in names})


def synthetic(rig: CameraGroup, frames: int, visibility: str, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts3d = rng.uniform(-1.5, 1.5, size=(frames, N_POINTS, 3))
    pts2d = rig.project(pts3d) + rng.normal(scale=2.0, size=(len(rig), frames, N_POINTS, 2))
    if visibility == "plan":
        seen = np.zeros((len(rig), N_POINTS), dtype=bool)
        seen[[0, 1, 2, 3], 19:] = True  # right-side cameras + front see the r* points
        seen[[3, 4, 5, 6], :19] = True  # left-side cameras + front see the l* points
        mask = seen[:, None, :] & (rng.random((len(rig), frames, N_POINTS)) > 0.1)
        pts2d[~mask] = np.nan
    outliers = rng.random(pts2d.shape[:-1]) < 0.05
    pts2d[outliers] += rng.uniform(-200, 200, size=(int(outliers.sum()), 2))
    return pts2d


def _svd_dlt(obs: np.ndarray, pmats: np.ndarray) -> np.ndarray:
    """One point, textbook linear least squares: normalized rows, SVD-based lstsq."""
    rows = []
    for (u, v), p in zip(obs, pmats):
        for r in (u * p[2] - p[0], v * p[2] - p[1]):
            rows.append(r / np.linalg.norm(r[:3]))
    rows = np.asarray(rows)
    return np.linalg.lstsq(rows[:, :3], -rows[:, 3], rcond=None)[0]


def loop_dlt(pts2d, pmats):
    out = np.full((*pts2d.shape[1:-1], 3), np.nan)
    for idx in np.ndindex(*pts2d.shape[1:-1]):
        obs = pts2d[(slice(None), *idx)]
        ok = np.isfinite(obs).all(axis=1)
        if ok.sum() >= 2:
            out[idx] = _svd_dlt(obs[ok], pmats[ok])
    return out


def loop_ransac(pts2d, pmats, threshold=15.0):
    out = np.full((*pts2d.shape[1:-1], 3), np.nan)
    for idx in np.ndindex(*pts2d.shape[1:-1]):
        obs = pts2d[(slice(None), *idx)]
        ok = np.flatnonzero(np.isfinite(obs).all(axis=1))
        best = (0, np.inf, None)
        for i, j in combinations(ok, 2):
            x = _svd_dlt(obs[[i, j]], pmats[[i, j]])
            hom = pmats[ok] @ np.append(x, 1.0)
            err = np.linalg.norm(hom[:, :2] / hom[:, 2:] - obs[ok], axis=1)
            inl = err < threshold
            key = (inl.sum(), err[inl].sum())
            if key[0] > best[0] or (key[0] == best[0] and key[1] < best[1]):
                best = (key[0], key[1], ok[inl])
        if best[0] >= 2:
            out[idx] = _svd_dlt(obs[best[2]], pmats[best[2]])
    return out


def _time(func, *args, repeat=3, **kwargs):
    """Best wall time and best CPU time (all threads) of ``repeat`` warm runs, first-call time."""
    start = time.perf_counter()
    func(*args, **kwargs)  # warm-up: compile
    first = time.perf_counter() - start
    wall = cpu = np.inf
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        func(*args, **kwargs)
        wall = min(wall, time.perf_counter() - start)
        cpu = min(cpu, time.process_time() - start_cpu)
    return wall, cpu, first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--loop-frames", type=int, default=20)
    args = parser.parse_args()
    rig = default_rig()
    pmats = rig.pmats
    for visibility in ("all", "plan"):
        pts2d = synthetic(rig, args.frames, visibility)
        small = pts2d[:, : args.loop_frames]
        loop_dlt_s = _time(loop_dlt, small, pmats, repeat=1)[0] / args.loop_frames
        loop_ransac_s = _time(loop_ransac, small, pmats, repeat=1)[0] / args.loop_frames
        print(f"visibility={visibility}  T={args.frames}  P={N_POINTS}  V={len(rig)}")
        print(
            "  (wall-clock frames/s; in brackets frames per CPU-second, robust to a loaded machine)"
        )
        for name, func, loop_s, target in (
            ("dlt", triangulate, loop_dlt_s, "100,000"),
            ("group", lambda cams, pts: cams.triangulate(pts), loop_dlt_s, "100,000"),
            (
                "np-dlt",
                lambda cams, pts: camera_model.dlt_solve(np, pts, cams.pmats),
                loop_dlt_s,
                "-",
            ),
            ("ransac", triangulate_ransac, loop_ransac_s, "20,000"),
            (
                "greedy",  # with the reprojection errors of the kept views
                lambda cams, pts: reconstruct(cams, pts, TriangulationParams(method="greedy")),
                None,
                "-",
            ),
        ):
            wall, cpu, first = _time(func, rig, pts2d)
            wall, cpu = wall / args.frames, cpu / args.frames
            vs_loop = f"{loop_s / wall:7.0f}x the per-point loop" if loop_s else " " * 27
            print(
                f"  {name:7s}{1 / wall:10,.0f} frames/s ({1 / cpu:8,.0f})  {vs_loop}   "
                f"first call {first:5.2f} s   target {target}"
            )
        print(
            f"  per-point loop: dlt {1 / loop_dlt_s:,.0f} frames/s, ransac {1 / loop_ransac_s:,.1f} frames/s"
        )
        # Agreement with the loop on the subset (independent SVD reference).
        ref = loop_dlt(small, pmats)
        got = triangulate(rig, small)
        print(f"  max |dlt - loop dlt| on the subset: {np.nanmax(np.abs(got - ref)):.2e}")


if __name__ == "__main__":
    main()
