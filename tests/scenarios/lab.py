"""What the lab scenarios share: a lab's folder, the run as a lab starts it, and the checks
every finished result must pass.

A lab runs the checkout's Snakefile from its own folder with its own config merged over
the default one (``snakemake -s <checkout>/Snakefile --configfile my.yaml``), so that is
how :func:`lab_run` runs it (unlike :func:`workflow_run.snakemake_command`, which hands
Snakemake a whole config).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import yaml

from workflow_run import REPO, SNAKEMAKE

#: The largest distance (px) the final 3D may lie from a 2D point it was solved from.
REPROJ_BOUND_PX = 40.0


def env() -> dict:
    """The environment of a lab's run: this checkout's flylib first on the path."""
    extra = os.environ.get("PYTHONPATH", "")
    environ = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), extra])}
    environ.pop("FLYLIB_RUN_ID", None)
    return environ


def flylib_cli(cwd: Path, *args: str, **environ: str) -> subprocess.CompletedProcess:
    """``python -m flylib.cli *args`` in ``cwd`` under :func:`env` (plus ``environ``);
    ``proc.out`` holds stdout then stderr."""
    proc = subprocess.run(
        [sys.executable, "-m", "flylib.cli", *args],
        cwd=cwd,
        env={**env(), **environ},
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    proc.out = proc.stdout + proc.stderr
    return proc


def write_config(path: Path, config: dict) -> Path:
    """The lab's own config file (only what differs from the default)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def lab_run(
    cwd: Path, configfile: str | Path, *args: str, timeout: float = 900
) -> subprocess.CompletedProcess:
    """``snakemake -s <checkout>/Snakefile --configfile <configfile> --cores 2 [args]`` run
    from ``cwd``; the output is in ``.out`` (stdout and stderr together)."""
    cmd = [
        str(SNAKEMAKE),
        "-s",
        str(REPO / "Snakefile"),
        "--configfile",
        str(configfile),
        "--cores",
        "2",
        *args,
    ]
    proc = subprocess.run(
        cmd, cwd=cwd, env=env(), capture_output=True, text=True, timeout=timeout, check=False
    )
    proc.out = proc.stdout + proc.stderr
    return proc


def finished(proc: subprocess.CompletedProcess) -> str:
    """The run's output, after asserting that it succeeded."""
    assert proc.returncode == 0, proc.out[-6000:]
    return proc.out


def copy_files(source: Path, dest: Path, patterns: list[str]) -> Path:
    """``dest`` holding copies of ``source``'s files matching ``patterns`` (a lab's folder)."""
    dest.mkdir(parents=True, exist_ok=True)
    for pattern in patterns:
        for path in sorted(source.glob(pattern)):
            shutil.copy(path, dest / path.name)
    return dest


def synthetic_recording(directory: Path, frames: int, seed: int = 0, cameras: dict | None = None):
    """A synthetic recording as the demo makes it (``camera_N.mp4``, the detector's 2D
    as DeepLabCut CSVs ``camera_NDLC_flylibdemo.csv``, ``truth.h5``), filmed by the
    default rig or by ``cameras`` (a ``cameras`` table replacing the default's).

    Returns the truth: ``points3d`` ``(T, P, 3)``, ``points2d`` ``(V, T, P, 2)``, ``views``.
    """
    from flylib.config import Config
    from flylib.demo import load_truth
    from flylib.pipeline.demo import make_demo

    data = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    if cameras is not None:
        data["cameras"] = cameras
    make_demo(Config.from_dict(data), directory, frames=frames, seed=seed)
    return load_truth(directory / "truth.h5")


def read_dlc_csv(path: Path, points: list[str]) -> np.ndarray:
    """``(T, P, 2)`` of a DeepLabCut CSV read with pandas (DeepLabCut's own layout:
    scorer / bodyparts / coords header rows, the frame as index), NaN where absent."""
    import pandas as pd

    table = pd.read_csv(path, header=[0, 1, 2], index_col=0)
    scorer = table.columns.get_level_values(0)[0]
    out = np.full((len(table), len(points), 2), np.nan)
    for p, name in enumerate(points):
        if (scorer, name, "x") in table.columns:
            out[:, p, 0] = table[(scorer, name, "x")].to_numpy(float)
            out[:, p, 1] = table[(scorer, name, "y")].to_numpy(float)
    return out


def stored_pose2d(results: Path) -> np.ndarray:
    """``pose2d/points`` of a results.h5: the 2D the run started from."""
    with h5py.File(results, "r") as f:
        return f["pose2d/points"][()]


def assert_self_consistent(results: Path, bound_px: float = REPROJ_BOUND_PX):
    """Assert that a results.h5 agrees with itself, and return its ``PoseResult``.

    - shapes: ``pts2d (V, T, P, 2)``, ``pts3d (T, P, 3)``, ``reproj_error (V, T, P)``;
    - the stored reprojection error is the distance between the stored 2D and the
      projection of the stored 3D by the stored cameras, NaN exactly where one is NaN;
    - the 2D the 3D was solved from is the run's 2D (``pose2d/points``) or missing
      (an outlier the triangulation dropped), never another value;
    - every used 2D point lies within ``bound_px`` of its 3D point's projection;
    - and flylib's own check (``flylib inspect --verify``) finds nothing.
    """
    from flylib.results import PoseResult
    from flylib.results.invariants import check_results

    assert check_results(results) == [], check_results(results)
    result = PoseResult.load(results)
    v, t, p, _ = result.pts2d.shape
    assert result.pts3d.shape == (t, p, 3) and result.reproj_error.shape == (v, t, p)
    assert len(result.cameras) == v
    distance = np.linalg.norm(result.pts2d - result.cameras.project(result.pts3d), axis=-1)
    np.testing.assert_array_equal(np.isnan(result.reproj_error), np.isnan(distance))
    np.testing.assert_allclose(result.reproj_error, distance, atol=1e-6, equal_nan=True)
    pose2d = stored_pose2d(results)
    used = np.isfinite(result.pts2d).all(-1)
    assert np.isfinite(pose2d[used]).all()
    np.testing.assert_array_equal(result.pts2d[used], pose2d[used])
    if used.any():
        assert np.nanmax(distance) < bound_px, np.nanmax(distance)
    return result


def table_line(out: str, recording: str) -> list[str]:
    """The cells of ``recording``'s line in the end-of-run table."""
    head, _, rest = out.partition("flylib: per-recording results")
    assert rest, f"no end-of-run table in the output:\n{out[-3000:]}"
    for line in rest.splitlines():
        cells = line.split()
        if cells and cells[0] == recording:
            return cells
    raise AssertionError(f"{recording} is not in the end-of-run table:\n{rest[:3000]}")


def similarity_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Median distance of ``estimate`` to ``truth`` ``(T, P, 3)`` after the best
    similarity transform, as a fraction of the truth's median distance from its centre
    (a reconstruction in its own gauge against a known one)."""
    from flylib.alignment import similarity_aligned

    ok = np.isfinite(estimate).all(-1) & np.isfinite(truth).all(-1)
    aligned = similarity_aligned(estimate[ok], truth[ok])
    extent = np.median(np.linalg.norm(truth[ok] - truth[ok].mean(0), axis=-1))
    return float(np.median(np.linalg.norm(aligned - truth[ok], axis=-1)) / extent)
