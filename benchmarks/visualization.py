"""Visualization benchmarks: render throughput and memory flatness.

1. Throughput: the two default videos (``pose2d``, ``pose3d``: 7-panel 960x960
   montages) rendered for the real ``../shared/data/deeperfly-example`` recording
   (7 x 960x480 H.264, 64 frames) with a synthetic fly's 2D/3D. Reported: montage
   frames/s, against two baselines measured in the same run: decoding the 7 streams
   alone (the floor) and rendering the two videos one after the other (two passes
   over the footage instead of one).
2. Memory: the default videos rendered from synthetic footage of 500 and of 5,000
   frames, each in a fresh process; the peak RSS ratio must stay within 2x.

Run: ``.venv/bin/python benchmarks/visualization.py [--quick]``
(``--quick``: 100 / 1,000 frames for the memory runs).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO.parent / "shared" / "data" / "deeperfly-example"
TARGET_FPS = 60.0


def make_result(n_frames: int, image_hw=(480, 960)):
    """A PoseResult of the default rig with a walking synthetic fly's 2D and 3D."""
    from flylib.camera.rig import CameraGroup
    from flylib.config import Config
    from flylib.demo import synthetic_fly
    from flylib.results import PoseResult
    from flylib.skeleton import Skeleton

    config = Config.default()
    views = [k for k in config.data["cameras"] if k != "defaults"]
    cameras = CameraGroup.from_config(config, image_sizes={v: image_hw for v in views})
    pts3d = synthetic_fly(n_frames)
    pts2d = cameras.project(pts3d)
    pts2d[:, ::17, 3] = np.nan  # some missing points
    return config, PoseResult(
        cameras=cameras,
        skeleton=Skeleton.from_config(config),
        pts2d=pts2d,
        pts3d=pts3d,
        image_sizes={v: image_hw for v in views},
    )


def cpu_seconds() -> float:
    """User + system CPU time of this process, all threads."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def decode_only(footage: dict) -> float:
    """Seconds to decode every frame of every view once (threaded PyAV, RGB)."""
    from flylib.io import open_reader

    start = time.perf_counter()
    for files in footage.values():
        for _ in open_reader(files).stream_frames():
            pass
    return time.perf_counter() - start


def throughput() -> None:
    from flylib.visualization import render_videos

    if not EXAMPLE.is_dir():
        print(f"skip throughput: {EXAMPLE} is absent")
        return
    config, _ = make_result(1)
    views = [k for k in config.data["cameras"] if k != "defaults"]
    footage = {v: [EXAMPLE / f"camera_{i}.mp4"] for i, v in enumerate(views)}
    from flylib.io import open_reader

    n_frames = open_reader(footage[views[0]]).count()
    _, result = make_result(n_frames)
    with tempfile.TemporaryDirectory() as tmp:
        render_videos(
            config.visualization, make_result(4)[1], footage, Path(tmp) / "warm", progress=False
        )
        t_decode = decode_only(footage)
        cpu0, start = cpu_seconds(), time.perf_counter()
        render_videos(config.visualization, result, footage, Path(tmp) / "one", progress=False)
        t_one = time.perf_counter() - start
        cpu_one = cpu_seconds() - cpu0
        start = time.perf_counter()
        for k in range(len(config.data["visualization"]["videos"])):
            data = copy.deepcopy(config.data)
            data["visualization"]["videos"] = [data["visualization"]["videos"][k]]
            render_videos(data["visualization"], result, footage, Path(tmp) / "sep", progress=False)
        t_sep = time.perf_counter() - start
    n_videos = len(config.data["visualization"]["videos"])
    montage_fps = n_frames * n_videos / t_one
    print(
        f"throughput: deeperfly-example, {n_frames} frames x 7 views 960x480, "
        f"{n_videos} default videos (960x960)"
    )
    print(f"  decode only (floor)          {n_frames / t_decode:8.1f} recording frames/s")
    print(
        f"  render, one pass (flylib)    {n_frames / t_one:8.1f} recording frames/s"
        f" = {montage_fps:.1f} montage frames/s"
    )
    print(f"  render, one video at a time  {n_frames / t_sep:8.1f} recording frames/s")
    print(
        f"  one pass vs separate passes: {t_sep / t_one:.2f}x faster; "
        f"render / decode time {t_one / t_decode:.2f}"
    )
    print(f"  montage frames/s vs target {TARGET_FPS:g}: {montage_fps / TARGET_FPS:.2f}")
    n_cpu = os.cpu_count() or 1
    cpu_fps = n_frames * n_videos / cpu_one * n_cpu
    print(
        f"  CPU time {1000 * cpu_one / (n_frames * n_videos):.1f} ms per montage frame "
        f"(all threads); CPU-bound rate on {n_cpu} idle cores: {cpu_fps:.1f} montage "
        f"frames/s ({cpu_fps / TARGET_FPS:.2f} of target); load average now "
        f"{os.getloadavg()[0]:.1f}"
    )


def make_footage(path: Path, n_frames: int, size=(320, 160)) -> None:
    """A synthetic clip: a moving gradient, so the decoder has real work."""
    from flylib.io import VideoWriter

    w, h = size
    xx, yy = np.meshgrid(np.arange(w), np.arange(h))
    with VideoWriter(path, fps=100, preset="ultrafast") as writer:
        for t in range(n_frames):
            gray = ((xx + 3 * t) % 256 + (yy // 8) * 4).astype(np.uint8)
            writer.write_frame(gray)


def memory_child(n_frames: int, clip: Path) -> None:
    """Render the default videos for ``n_frames`` and print peak RSS as JSON."""
    from flylib.visualization import render_videos

    config, result = make_result(n_frames, image_hw=(480, 960))
    views = list(result.cameras.names)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        start = time.perf_counter()
        render_videos(config.visualization, result, {v: [clip] for v in views}, tmp, progress=False)
        seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(
        json.dumps({"frames": n_frames, "before_kib": before, "peak_kib": peak, "seconds": seconds})
    )


def memory(short: int, long: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        clip = Path(tmp) / "clip.mp4"
        make_footage(clip, long)
        rows = []
        for n in (short, long):
            out = subprocess.run(
                [sys.executable, __file__, "--memory-child", str(n), str(clip)],
                check=True,
                capture_output=True,
                text=True,
            )
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(
        "memory: default videos from synthetic footage (320x160 clip upscaled), "
        "fresh process per run"
    )
    for r in rows:
        print(
            f"  {r['frames']:6d} frames: peak RSS {r['peak_kib'] / 1024:7.1f} MiB "
            f"(before render {r['before_kib'] / 1024:7.1f} MiB), "
            f"{r['frames'] * 2 / r['seconds']:.1f} montage frames/s"
        )
    ratio = rows[1]["peak_kib"] / rows[0]["peak_kib"]
    growth = (rows[1]["peak_kib"] - rows[1]["before_kib"]) / 1024
    print(
        f"  peak ratio {long}/{short} frames: {ratio:.3f} (limit 2.0); "
        f"render growth at {long} frames: {growth:.1f} MiB"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--memory-child", nargs=2, metavar=("FRAMES", "CLIP"))
    args = parser.parse_args()
    if args.memory_child:
        memory_child(int(args.memory_child[0]), Path(args.memory_child[1]))
        return
    warnings.simplefilter("ignore")
    throughput()
    if not args.skip_memory:
        memory(*((100, 1000) if args.quick else (500, 5000)))


if __name__ == "__main__":
    main()
