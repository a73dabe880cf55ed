"""Peak memory of each stage script against the recording's size, and the workflow's
``mem_mb`` formula beside it (what SLURM reserves, ``flylib.pipeline.memory``).

For each frame count, a synthetic tethered fly is seen by the default 7-camera rig
(noise, dropouts, gross outliers as the demo adds them) and saved as the pose2d
artifact; then every later stage runs as its own script process, exactly as a
workflow job does (with its rule's threads), and its peak resident memory is read from the
kernel (``wait4``'s ``ru_maxrss``). Printed per stage: the peak at each size, the
growth per million (frame, point, view) elements between the smallest and largest
size, the ``mem_mb`` the rule declares, and its ratio to the peak (must be > 1).
The 2D import (pose2d) and visualization read footage and are not measured here.

Run: ``.venv/bin/python benchmarks/stage_memory.py [--frames 500 5000]``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = REPO / "scripts"


def _pose2d(config, path: Path, frames: int) -> tuple[int, int, int]:
    """The synthetic pose2d artifact; returns its (V, T, P)."""
    from flylib.camera.rig import CameraGroup
    from flylib.demo import demo_settings, observe, synthetic_fly, view_visibility
    from flylib.interop.df3d import FLY38_POINT_NAMES
    from flylib.pipeline.inputs import stage_params
    from flylib.provenance import stage_provenance
    from flylib.results import Pose2dData

    skeleton = config.skeleton()
    points = list(skeleton.point_names)
    order = [list(FLY38_POINT_NAMES).index(p) for p in points]
    pts3d = synthetic_fly(frames, 0)[:, order]
    settings = demo_settings({"frames": frames})
    size = (settings["height"], settings["width"])
    views = config.view_names()
    cameras = CameraGroup.from_config(config, image_sizes={v: size for v in views})
    clean = np.asarray(cameras.project(pts3d), dtype=np.float64)
    pts2d, conf = observe(
        clean,
        view_visibility((config.data.get("pose2d") or {}).get("output_points"), views, points),
        settings,
        size,
    )
    Pose2dData(pts2d=pts2d, conf=conf, view_names=views, image_sizes={v: size for v in views}).save(
        path, skeleton, meta=stage_provenance(stage_params(config, "pose2d"), "pose2d")
    )
    return pts2d.shape[0], frames, pts2d.shape[2]


def _peak_mb(args: list[str], cwd: Path) -> float:
    """Run a stage script; its peak resident memory in MB (the kernel's ru_maxrss)."""
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.Popen(
        [sys.executable, *args], cwd=cwd, env=env, stderr=subprocess.PIPE, text=True
    )
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{args[0]} failed:\n{proc.stderr.read()[-3000:]}")
    return usage.ru_maxrss / 1024.0


#: The threads each rule declares (workflow/rules/*.smk): thread pools hold chunks in
#: flight, so memory is measured as the job runs.
THREADS = {
    "bundle_adjustment": 1,
    "triangulation": 2,
    "refinement": 2,
    "assemble": 1,
    "kinematics": 1,
}


def _stages(config_path: Path, work: Path) -> dict[str, list[str]]:
    out = work / "out"
    stages = out / "stages"

    def common(stage: str) -> list[str]:
        return ["--config", str(config_path), "--threads", str(THREADS[stage])]

    return {
        "bundle_adjustment": [
            str(SCRIPTS / "bundle_adjustment.py"),
            *common("bundle_adjustment"),
            "--pose2d",
            str(stages / "pose2d.h5"),
            "--out",
            str(stages / "bundle_adjustment.h5"),
        ],
        "triangulation": [
            str(SCRIPTS / "triangulation.py"),
            *common("triangulation"),
            "--pose2d",
            str(stages / "pose2d.h5"),
            "--bundle-adjustment",
            str(stages / "bundle_adjustment.h5"),
            "--out",
            str(stages / "triangulation.h5"),
        ],
        "refinement": [
            str(SCRIPTS / "refinement.py"),
            *common("refinement"),
            "--pose2d",
            str(stages / "pose2d.h5"),
            "--triangulation",
            str(stages / "triangulation.h5"),
            "--bundle-adjustment",
            str(stages / "bundle_adjustment.h5"),
            "--out",
            str(stages / "refinement.h5"),
        ],
        "assemble": [
            str(SCRIPTS / "assemble.py"),
            *common("assemble"),
            "--pose2d",
            str(stages / "pose2d.h5"),
            "--bundle-adjustment",
            str(stages / "bundle_adjustment.h5"),
            "--triangulation",
            str(stages / "triangulation.h5"),
            "--refinement",
            str(stages / "refinement.h5"),
            "--outdir",
            str(out),
        ],
        "kinematics": [
            str(SCRIPTS / "kinematics.py"),
            *common("kinematics"),
            "--results",
            str(out / "results.h5"),
            "--outdir",
            str(out),
        ],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[500, 5000])
    args = parser.parse_args()

    from flylib.config import Config
    from flylib.pipeline.memory import stage_mem_mb

    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    peaks: dict[str, list[float]] = {}
    sizes = []
    with tempfile.TemporaryDirectory() as tmp:
        for frames in sorted(args.frames):
            work = Path(tmp) / f"T{frames}"
            (work / "out" / "stages").mkdir(parents=True)
            config_path = work / "config.yaml"
            config_path.write_text(yaml.safe_dump(data, sort_keys=False))
            shape = _pose2d(Config.from_file(config_path), work / "out/stages/pose2d.h5", frames)
            sizes.append(shape)
            for stage, cmd in _stages(config_path, work).items():
                peaks.setdefault(stage, []).append(_peak_mb(cmd, work))
    elements = [v * t * p / 1e6 for v, t, p in sizes]
    print(f"sizes (V, T, P): {sizes}; elements (M): {[round(e, 3) for e in elements]}")
    print(
        f"{'stage':20s}"
        + "".join(f"{f'peak MB T={t}':>16s}" for _, t, _ in sizes)
        + f"{'MB / M elem':>13s}"
        + "".join(f"{f'mem_mb T={t}':>14s}{'ratio':>7s}" for _, t, _ in sizes)
    )
    for stage, values in peaks.items():
        slope = (values[-1] - values[0]) / max(elements[-1] - elements[0], 1e-9)
        declared = [stage_mem_mb(stage, shape) for shape in sizes]
        print(
            f"{stage:20s}"
            + "".join(f"{v:16.0f}" for v in values)
            + f"{slope:13.0f}"
            + "".join(f"{d:14d}{d / v:7.2f}" for d, v in zip(declared, values))
        )


if __name__ == "__main__":
    main()
