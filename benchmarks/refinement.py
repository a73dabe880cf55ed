"""Spatiotemporal refinement: accuracy against a synthetic truth, speed, and memory.

    PYTHONPATH=src python benchmarks/refinement.py                  # everything
    PYTHONPATH=src python benchmarks/refinement.py --skip-memory    # accuracy + speed only
    PYTHONPATH=src python benchmarks/refinement.py --skip-memory --baseline ''   # no old-solver timing

The scene is the issue's acceptance scene: the synthetic walking fly (constant bones,
fixed thorax) seen by the default 7-camera rig, with detector-like 2D errors (1.5 px
noise, 5% gross outliers up to 50 px, 2% left/right swaps in the side views, 10%
missing). The baseline, measured in the same run, is RANSAC triangulation alone
(the pipeline's default before refinement).

Printed:
- 3D error against the truth (median, 95th percentile) of RANSAC and of the
  refinement on the points both reconstruct, their ratio, the points the refinement
  adds (single-view points RANSAC cannot triangulate), and how many points RANSAC had
  right (error < 5% of the median bone) that the refinement made worse by more than
  5% of a bone;
- speed: frames/s of the refinement with the JIT compilation excluded (the first call
  in the process compiles; its extra time is printed separately), beside RANSAC's, and
  frames per CPU second (all threads: the figure least moved by other work on the
  machine); then the solver of git revision ``--baseline`` (default: the one before
  the speed work) timed on the same scene in a child process, and the speed-ups;
- memory: the peak resident memory of a fresh process running the refinement stage
  on artifacts of 10,000 and 100,000 frames (streamed chunk by chunk), and the ratio.

The machine is shared; timings vary with the load (ratios within one run are the
meaningful figures).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: The solver before the speed work of issue #16 (whole-chunk LM, padded frames free,
#: band copied in C order): timed beside the current one unless ``--baseline ''``.
BASELINE = "bfd9509"
sys.path.insert(0, str(REPO / "tests"))

from flylib.demo import synthetic_fly
from flylib.refinement import refine_points, skeleton_terms
from flylib.skeleton import Skeleton
from flylib.triangulation import reconstruct

from synthetic import POINT_NAMES, default_rig, detector_errors, rig_visibility


def scene(frames: int, seed: int = 3):
    rig = default_rig()
    truth = synthetic_fly(frames, seed=seed)
    clean = np.asarray(rig.project(truth))
    pts2d, conf, kind = detector_errors(
        clean, rig_visibility(rig.names), rig.names, POINT_NAMES, seed=seed + 1
    )
    return rig, truth, pts2d, conf, kind


def accuracy_and_speed(frames: int) -> None:
    rig, truth, pts2d, conf, kind = scene(frames)
    terms = skeleton_terms(Skeleton.fly(), None)
    started = time.perf_counter()
    start, clean2d, _ = reconstruct(rig, pts2d)
    ransac_s = time.perf_counter() - started
    inliers = np.isfinite(clean2d).all(-1)

    first, result, speed = timed_refinement(rig, pts2d, start, conf, inliers, terms)
    solve_s = speed["seconds"]
    assert np.array_equal(first.points3d, result.points3d, equal_nan=True)

    before = np.linalg.norm(start - truth, axis=-1)
    after = np.linalg.norm(result.points3d - truth, axis=-1)
    both = np.isfinite(before) & np.isfinite(after)
    bones = terms["bones"]
    bone = float(np.median(np.linalg.norm(truth[:, bones[:, 0]] - truth[:, bones[:, 1]], axis=-1)))
    right = both & (before < 0.05 * bone)
    worse = int(((after - before) > 0.05 * bone)[right].sum())
    rows = [("ransac", before[both]), ("refinement", after[both])]
    print(
        f"scene: {frames} frames x 38 points x 7 views; 1.5 px noise, 5% outliers <= 50 px, "
        f"2% L/R swaps (side views), 10% missing; median bone {bone:.3f}"
    )
    print(
        f"{'':12s} {'median':>9s} {'p95':>9s}  (world units, {both.sum()} points both reconstruct)"
    )
    for name, err in rows:
        print(f"{name:12s} {np.median(err):9.5f} {np.percentile(err, 95):9.5f}")
    print(
        f"ratio        {np.median(after[both]) / np.median(before[both]):9.3f} "
        f"{np.percentile(after[both], 95) / np.percentile(before[both], 95):9.3f}   "
        "(target: <= 0.60 median, <= 0.40 p95)"
    )
    print(
        f"coverage: ransac {np.isfinite(before).mean():.3f}, refinement {np.isfinite(after).mean():.3f}; "
        f"refinement alone on its own points: median {np.nanmedian(after):.5f}, "
        f"p95 {np.nanpercentile(after, 95):.5f}"
    )
    print(
        f"points ransac had right (< 5% of a bone) made worse by > 5% of a bone: {worse} of {right.sum()} "
        f"(largest increase {np.max((after - before)[right]):.4f}; 5% of a bone = {0.05 * bone:.4f})"
    )
    observed = np.isfinite(pts2d).all(-1)
    rejected = observed & ~np.isfinite(result.points2d).all(-1)
    for label, code in (("outliers", 1), ("swaps", 2), ("good", 0)):
        total = int((kind == code).sum())
        print(f"  {label:8s}: {int((rejected & (kind == code)).sum())} of {total} rejected")
    print(
        f"speed: refinement {frames / solve_s:,.0f} frames/s (JIT excluded; {solve_s:.2f} s; "
        f"{result.info['chunks']} chunks, LM steps per chunk {result.info['iterations'][:4]}), "
        f"ransac {frames / ransac_s:,.0f} frames/s; ratio ransac/refinement {solve_s / ransac_s:.1f}x "
        "(target: >= 2,000 frames/s)"
    )
    print(
        f"       per CPU second: {frames / speed['cpu_seconds']:,.0f} frames (all threads; less "
        f"sensitive to the machine's load, {speed['load']:.1f} during the run)"
    )
    print(
        f"JIT: the first call in this process took {speed['first_seconds']:.2f} s for {frames} frames "
        f"(compilation ~{speed['jit_seconds']:.2f} s; a 64-frame call first: {speed['small_first']:.2f} s)"
    )
    return frames / solve_s, frames / speed["cpu_seconds"]


def timed_refinement(rig, pts2d, start, conf, inliers, terms):
    """Refine twice (the first call compiles); ``(first, second, figures)``."""
    started = time.perf_counter()
    refine_points(
        pts2d[:, :64], rig, start[:64], conf=conf[:, :64], inliers=inliers[:, :64], **terms
    )
    small_first = time.perf_counter() - started
    started = time.perf_counter()
    first = refine_points(pts2d, rig, start, conf=conf, inliers=inliers, **terms)
    first_s = time.perf_counter() - started
    started, cpu = time.perf_counter(), time.process_time()
    result = refine_points(pts2d, rig, start, conf=conf, inliers=inliers, **terms)
    solve_s, cpu_s = time.perf_counter() - started, time.process_time() - cpu
    return (
        first,
        result,
        {
            "seconds": solve_s,
            "cpu_seconds": cpu_s,
            "first_seconds": first_s,
            "jit_seconds": max(first_s - solve_s, 0.0),
            "small_first": small_first,
            "load": os.getloadavg()[0],
        },
    )


def speed_child(frames: int) -> None:
    """Time the refinement on the scene (whatever ``flylib`` is importable); print JSON."""
    rig, _truth, pts2d, conf, _kind = scene(frames)
    from flylib.triangulation import reconstruct_ransac  # the baseline's (points first)

    terms = skeleton_terms(Skeleton.fly(), None)
    start, clean2d, _ = reconstruct_ransac(pts2d, rig, 15.0, 2)
    _, _, figures = timed_refinement(rig, pts2d, start, conf, np.isfinite(clean2d).all(-1), terms)
    print(json.dumps(figures))


def baseline(frames: int, revision: str, figures: tuple[float, float]) -> None:
    """The refinement of git ``revision`` timed on the same scene, in a child process
    (its ``src`` and ``config`` exported to a temporary directory)."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            archive = subprocess.run(
                ["git", "-C", str(REPO), "archive", revision, "src", "config"],
                capture_output=True,
                check=True,
            ).stdout
            subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
            proc = subprocess.run(
                [sys.executable, __file__, "--speed-child", str(frames)],
                capture_output=True,
                text=True,
                check=True,
                env={**os.environ, "PYTHONPATH": f"{tmp}/src"},
            )
        except (subprocess.CalledProcessError, FileNotFoundError) as exc:
            print(f"baseline {revision}: not measured ({exc})")
            return
    old = json.loads(proc.stdout.strip().splitlines()[-1])
    wall, cpu = frames / old["seconds"], frames / old["cpu_seconds"]
    print(
        f"baseline solver ({revision}, same scene, measured next): {wall:,.0f} frames/s, "
        f"{cpu:,.0f} per CPU second (JIT ~{old['jit_seconds']:.2f} s, load {old['load']:.1f}); "
        f"this solver {figures[0] / wall:.2f}x wall, {figures[1] / cpu:.2f}x per CPU second"
    )


def write_artifacts(directory: Path, frames: int, block: int = 10000) -> tuple[Path, Path]:
    """pose2d.h5 and triangulation.h5 of the scene, generated and written block by block."""
    import h5py

    from flylib.results import new_meta

    rig = default_rig()
    vis = rig_visibility(rig.names)
    truth = synthetic_fly(frames, seed=7)
    n_views, n_points = len(rig.names), len(POINT_NAMES)
    p2d_path, tri_path = directory / "pose2d.h5", directory / "triangulation.h5"
    with h5py.File(p2d_path, "w") as p2d, h5py.File(tri_path, "w") as tri:
        p2d.attrs["meta"] = json.dumps(new_meta("pose2d"))
        tri.attrs["meta"] = json.dumps(new_meta("triangulation"))
        g = p2d.create_group("pose2d")
        g.attrs["view_names"] = json.dumps(list(rig.names))
        g.attrs["image_sizes"] = json.dumps({v: [480, 960] for v in rig.names})
        kw = {"compression": "gzip", "compression_opts": 1, "dtype": "f8"}
        points = g.create_dataset(
            "points", (n_views, frames, n_points, 2), chunks=(n_views, 1024, n_points, 2), **kw
        )
        conf = g.create_dataset(
            "conf", (n_views, frames, n_points), chunks=(n_views, 1024, n_points), **kw
        )
        t = tri.create_group("triangulation")
        t2d = t.create_dataset(
            "points", (n_views, frames, n_points, 2), chunks=(n_views, 1024, n_points, 2), **kw
        )
        t3d = t.create_dataset("points3d", (frames, n_points, 3), chunks=(1024, n_points, 3), **kw)
        for lo in range(0, frames, block):
            hi = min(lo + block, frames)
            clean = np.asarray(rig.project(truth[lo:hi]))
            pts, c, _ = detector_errors(clean, vis, rig.names, POINT_NAMES, seed=lo)
            start, clean2d, _ = reconstruct(rig, pts)
            points[:, lo:hi], conf[:, lo:hi], t2d[:, lo:hi], t3d[lo:hi] = pts, c, clean2d, start
    return p2d_path, tri_path


def memory_child(directory: Path) -> None:
    """Run the refinement stage on the artifacts in ``directory``; print JSON figures."""
    from flylib.config import Config
    from flylib.pipeline.refinement import run_refinement
    from flylib.pipeline.stage_helpers import run_inputs

    inputs = run_inputs(Config.default(), "refinement")
    before = _peak_mb()
    started = time.perf_counter()
    run_refinement(
        inputs, directory / "pose2d.h5", directory / "triangulation.h5", directory / "refinement.h5"
    )
    seconds = time.perf_counter() - started
    print(json.dumps({"peak_mb": _peak_mb(), "before_mb": before, "seconds": seconds}))


def _peak_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss, not inherited
    from the parent across fork + exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def memory(sizes: list[int]) -> None:
    figures = {}
    for frames in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            directory = Path(tmp)
            started = time.perf_counter()
            write_artifacts(directory, frames)
            made = time.perf_counter() - started
            proc = subprocess.run(
                [sys.executable, __file__, "--memory-child", str(directory)],
                capture_output=True,
                text=True,
                check=True,
            )
            figures[frames] = json.loads(proc.stdout.strip().splitlines()[-1])
            f = figures[frames]
            print(
                f"memory: {frames:,} frames: peak {f['peak_mb']:.0f} MB (imports and set-up "
                f"{f['before_mb']:.0f} MB), stage {f['seconds']:.1f} s = {frames / f['seconds']:,.0f} frames/s "
                f"including HDF5 reading/writing and the JIT (artifacts made in {made:.0f} s)"
            )
    if len(sizes) == 2:
        a, b = (figures[s]["peak_mb"] for s in sizes)
        print(f"memory ratio {sizes[1]:,} / {sizes[0]:,} frames: {b / a:.2f}x (target <= 1.5x)")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--frames", type=int, default=2000, help="frames of the accuracy/speed scene"
    )
    parser.add_argument(
        "--memory-frames",
        type=int,
        nargs=2,
        default=[10000, 100000],
        help="the two recording lengths of the memory comparison",
    )
    parser.add_argument("--skip-memory", action="store_true", help="accuracy and speed only")
    parser.add_argument(
        "--baseline",
        default=BASELINE,
        help="git revision whose solver is timed on the same scene for comparison ('' to skip)",
    )
    parser.add_argument("--memory-child", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--speed-child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.memory_child:
        memory_child(args.memory_child)
        return
    if args.speed_child:
        speed_child(args.speed_child)
        return
    figures = accuracy_and_speed(args.frames)
    if args.baseline:
        baseline(args.frames, args.baseline, figures)
    if not args.skip_memory:
        memory(list(args.memory_frames))


if __name__ == "__main__":
    main()
