"""results.h5 size and speed for a long recording on the default 7-camera, 38-point rig.

Writes the pose2d artifact and a triangulation artifact for T frames, assembles
results.h5 and loads it back, with flylib's chunked gzip storage and, as the baseline
measured in the same run, plain contiguous float64 datasets. Two kinds of 2D:

* ``grid``: arg-max detections on the 64x128 heatmap grid (7.5 px steps, as DeepFly2D
  stores them), NaN where the detection plan gives a (view, point) no pathway;
* ``subpixel``: continuous coordinates (the worst case for compression).

Targets: results.h5 at most 50% of the raw float64 bytes for grid 2D (random
confidences and errors do not compress, so subpixel 2D sits near that bound), and
loading it at most 5x slower than reading the same arrays uncompressed.

Checksums: every dataset carries HDF5's Fletcher-32 filter (issue 13). The same
writes, assembly and load are timed with the checksums off (the baseline, same run,
best of ``--repeat``), and the overhead is printed; target < 10% on write and read.

Run: ``.venv/bin/python benchmarks/results_io.py [--frames 20000]``
(``--frames 100000`` needs about 3 GB of memory.)
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from flylib.config import Config
from flylib.demo import view_visibility
from flylib.pipeline.planning import config_rig
from flylib.results import (
    Pose2dData,
    PoseResult,
    assemble_results,
    datasets as results_datasets,
    write_stage,
)


def visibility(config: Config) -> np.ndarray:
    """``(V, P)``: which (view, point) the default detection plan fills."""
    return view_visibility(
        (config.data.get("pose2d") or {}).get("output_points"),
        config.view_names(),
        list(config.skeleton().point_names),
    )


def make_arrays(config: Config, n_frames: int, kind: str, rng: np.random.Generator) -> dict:
    seen = visibility(config)
    v, p = seen.shape
    pts2d = rng.uniform([0, 0], [960, 480], size=(v, n_frames, p, 2))
    if kind == "grid":
        pts2d = np.round(pts2d / 7.5) * 7.5
    pts2d[~np.broadcast_to(seen[:, None, :], (v, n_frames, p))] = np.nan
    conf = np.where(np.isnan(pts2d[..., 0]), np.nan, rng.uniform(size=(v, n_frames, p)))
    pts3d = rng.normal(size=(n_frames, p, 3))
    reproj = np.where(np.isnan(conf), np.nan, rng.gamma(2.0, 2.0, size=conf.shape))
    return {"pts2d": pts2d, "conf": conf, "pts3d": pts3d, "reproj": reproj}


def write_plain(path: Path, arrays: dict) -> None:
    with h5py.File(path, "w") as f:
        for name, arr in arrays.items():
            f.create_dataset(name, data=arr)


def read_plain(path: Path) -> None:
    with h5py.File(path, "r") as f:
        for name in f:
            f[name][()]


class _Clock:
    """Wall and CPU (all threads of this process) seconds of a block."""

    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu


def write_and_load(config: Config, arrays: dict, stages: Path, checksums: bool) -> dict:
    """Stage writes, assembly and load of results.h5, with or without Fletcher-32:
    ``{step: (wall s, cpu s)}``."""
    skeleton, rig = (
        config.skeleton(),
        config_rig(config, {v: (480, 960) for v in config.view_names()}),
    )
    results_datasets.FLETCHER32 = checksums
    try:
        with _Clock() as write:
            Pose2dData(arrays["pts2d"], arrays["conf"], config.view_names(), {}).save(
                stages / "pose2d.h5", skeleton
            )
            write_stage(
                stages / "triangulation.h5",
                "triangulation",
                {
                    "points": arrays["pts2d"],
                    "points3d": arrays["pts3d"],
                    "reproj_error": arrays["reproj"],
                },
            )
        with _Clock() as assemble:
            assemble_results(
                stages / "results.h5",
                skeleton=skeleton,
                config_rig=rig,
                stage_files={
                    "pose2d": stages / "pose2d.h5",
                    "triangulation": stages / "triangulation.h5",
                },
                verify=False,  # synthetic arrays, not a solved pose
            )
    finally:
        results_datasets.FLETCHER32 = True
    with _Clock() as load:
        PoseResult.load(stages / "results.h5")
    return {
        name: (c.wall, c.cpu)
        for name, c in (("write", write), ("assemble", assemble), ("load", load))
    }


def checksum_overhead(n_frames: int, kind: str, workdir: Path, repeat: int) -> None:
    """Print the write/assemble/load time with and without Fletcher-32 checksums.

    Wall time is the user's figure; CPU time (summed over the deflate threads) is the
    steadier one on a shared machine. Both are the best of ``repeat`` interleaved runs.
    """
    config = Config.default()
    arrays = make_arrays(config, n_frames, kind, np.random.default_rng(0))
    best: dict[bool, dict] = {}
    for _ in range(repeat):
        for checksums in (False, True):  # interleaved, so load drifts hit both alike
            times = write_and_load(config, arrays, workdir / f"{kind}_{checksums}", checksums)
            prev = best.setdefault(checksums, times)
            best[checksums] = {k: tuple(map(min, v, prev[k])) for k, v in times.items()}
    off, on = best[False], best[True]
    cells = []
    ok = True
    for key in ("write", "assemble", "load"):
        wall = on[key][0] / max(off[key][0], 1e-9) - 1
        cpu = on[key][1] / max(off[key][1], 1e-9) - 1
        ok &= key == "assemble" or min(wall, cpu) < 0.10
        cells.append(
            f"{key} wall {off[key][0]:5.2f} -> {on[key][0]:5.2f} s ({wall:+6.1%}), "
            f"cpu {off[key][1]:5.2f} -> {on[key][1]:5.2f} s ({cpu:+6.1%})"
        )
    print(
        f"[{'PASS' if ok else 'MISS'}] checksums {kind:9s} T={n_frames:>7,d} without -> with Fletcher-32: "
        + "; ".join(cells)
        + f" (best of {repeat}; target < 10% on write and load; assemble without "
        "checksums has nothing to verify)"
    )


def run(n_frames: int, kind: str, workdir: Path) -> None:
    config = Config.default()
    skeleton, rig = (
        config.skeleton(),
        config_rig(config, {v: (480, 960) for v in config.view_names()}),
    )
    arrays = make_arrays(config, n_frames, kind, np.random.default_rng(0))
    raw_bytes = sum(a.nbytes for a in arrays.values()) + arrays["pts2d"].nbytes  # 2D stored twice

    plain = workdir / f"plain_{kind}.h5"
    t0 = time.perf_counter()
    write_plain(plain, {**arrays, "pts2d_clean": arrays["pts2d"]})
    plain_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    read_plain(plain)
    plain_read = time.perf_counter() - t0

    stages = workdir / kind
    t0 = time.perf_counter()
    Pose2dData(arrays["pts2d"], arrays["conf"], config.view_names(), {}).save(
        stages / "pose2d.h5", skeleton
    )
    write_stage(
        stages / "triangulation.h5",
        "triangulation",
        {"points": arrays["pts2d"], "points3d": arrays["pts3d"], "reproj_error": arrays["reproj"]},
    )
    stage_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    assemble_results(
        stages / "results.h5",
        skeleton=skeleton,
        config_rig=rig,
        stage_files={"pose2d": stages / "pose2d.h5", "triangulation": stages / "triangulation.h5"},
        verify=False,  # synthetic arrays, not a solved pose
    )
    assemble = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = PoseResult.load(stages / "results.h5")
    load = time.perf_counter() - t0
    assert np.array_equal(result.pts2d, arrays["pts2d"], equal_nan=True)

    size = (stages / "results.h5").stat().st_size
    ratio, slowdown = size / raw_bytes, load / max(plain_read, 1e-9)
    ok = (ratio <= 0.5 or kind != "grid") and slowdown <= 5.0
    print(
        f"[{'PASS' if ok else 'MISS'}] {kind:9s} T={n_frames:>7,d}  raw {raw_bytes / 2**20:8.1f} MiB"
        f" | plain h5 {plain.stat().st_size / 2**20:8.1f} MiB, write {plain_write:5.2f} s, read {plain_read:5.2f} s"
        f" | flylib results.h5 {size / 2**20:8.1f} MiB ({ratio:5.1%} of raw),"
        f" stage writes {stage_write:5.2f} s, assemble {assemble:5.2f} s,"
        f" load {load:5.2f} s ({slowdown:4.1f}x plain read)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument(
        "--repeat", type=int, default=3, help="runs per checksum setting (best is kept)"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("grid", "subpixel"):
            run(args.frames, kind, Path(tmp))
        for kind in ("grid", "subpixel"):
            checksum_overhead(args.frames, kind, Path(tmp), args.repeat)


if __name__ == "__main__":
    main()
