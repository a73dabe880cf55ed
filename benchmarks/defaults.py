"""Bundle adjustment's ``points_to_use`` default, judged on real data (issue 46).

Each candidate ``bundle_adjustment.points_to_use`` (the 30 leg joints, the default before
issue 46; legs and antennae, the default since, marked ``*``; legs and abdomen; every point)
and, as the baseline, no bundle adjustment, through :func:`flylib.run_from_points2d` (the
default config otherwise), on four datasets:

- ``sample``: DeepFly3D's sample recording, its ``df3d_result_2d.pkl`` imported as a user
  does (the front camera blind, the two sides share no view), 15 frames, from the default
  config's rig; reference: DeepFly3D's own 3D of the recording (the package example's).
- ``package``: DeepFly3D 1.x's package example, its 2D in pixels (the front camera sees
  both sides), 15 frames, from the default config's rig; reference: its own 3D.
- ``rough rig``: the synthetic tethered fly seen by a DeepFly3D-like rig from a rough
  start (``tests/rough_rig.py``: 1 px noise, 5 % outliers), the first ``--frames``
  (default 200) frames, 7 cameras.
- ``4 cameras``: the same scene seen by rh, rf, lf, lh only (issue 46's fewer-camera rig:
  each point has two views, so no held-out view).

Printed per candidate and dataset: the 3D error after the best similarity or mirrored
similarity (the default rig explains DeepFly3D's images with the mirror-image world) in
median bone lengths of the reference, the held-out-view error (median px, DLT; n/a where
no point has a third view) and the seconds (JIT warmed first). The frame cap keeps it to
about three minutes on a 2-core machine; the real datasets need ``../shared/data`` and are
skipped, with a line, without it.

Run: ``PYTHONPATH=src python benchmarks/defaults.py [--frames 200]``
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import warnings
from pathlib import Path

# OpenBLAS threads spin against each other on a loaded 2-core machine (as in bundle_adjustment.py)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

import front_blind  # noqa: E402

from flylib import run_from_points2d  # noqa: E402
from flylib.config import Config  # noqa: E402
from flylib.skeleton import Skeleton  # noqa: E402

import rough_rig  # noqa: E402
from rig_constants import VIEWS  # noqa: E402

SKELETON = Skeleton.fly()
LEGS = [p for p in SKELETON.point_names if p[:2] in ("lf", "lm", "lh", "rf", "rm", "rh")]
#: label -> ``points_to_use`` (``False``: no bundle adjustment, the baseline)
CANDIDATES = {
    "no bundle adjustment": False,
    "leg joints (30)": LEGS,
    "legs + antennae (32)": [*LEGS, "l_antenna", "r_antenna"],
    "legs + abdomen (36)": [*LEGS, *(p for p in SKELETON.point_names if "abdomen" in p)],
    "all points (null)": None,
}
FOUR = ("rh", "rf", "lf", "lh")


def real_datasets() -> dict:
    """``{name: (start rig, pts2d, conf, reference 3D)}`` of the two DeepFly3D results."""
    from flylib.interop.importer import import_points2d
    from flylib.pipeline.pose2d import import_target

    if not front_blind.available():
        print(f"- skipped sample and package: {front_blind.PACKAGE_EXAMPLE.parent} is absent")
        return {}
    spec = {"format": "deepfly3d", "files": front_blind.SAMPLE_2D.name}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the blind front camera is warned about
        sample = import_points2d(
            import_target(Config.default()), front_blind.SAMPLE_2D.parent, spec
        )
    truth, start = front_blind.recorded_poses(), front_blind.default_start()
    return {
        "sample": (start, sample.pts2d, sample.conf, truth),
        "package": (start, front_blind.package_points2d(), None, truth),
    }


def synthetic_datasets(frames: int) -> dict:
    """``{name: (start rig, pts2d, conf, truth)}`` of the rough-rig scene, 7 and 4 cameras."""
    case = rough_rig.make_case(frames)
    four = [VIEWS.index(v) for v in FOUR]
    return {
        "rough rig": (case.start, case.pts2d, case.conf, case.truth),
        "4 cameras": (case.start.subset(FOUR), case.pts2d[four], case.conf[four], case.truth),
    }


def score(dataset, points_to_use) -> tuple[float, float, float]:
    """``(3D error in median bones, held-out median px, seconds)`` of one fit."""
    start, pts2d, conf, truth = dataset
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_from_points2d(
            start,
            SKELETON,
            pts2d,
            conf,
            do_bundle_adjust=points_to_use is not False,
            bundle_adjust_kwargs={"points_to_use": points_to_use or None},
        )
    seconds = time.perf_counter() - t0
    bones = np.asarray(SKELETON.bones, int)
    unit = np.nanmedian(np.linalg.norm(truth[:, bones[:, 0]] - truth[:, bones[:, 1]], axis=-1))
    error = np.nanmedian(front_blind.mirror_free_error(np.asarray(result.pts3d, float), truth))
    held = front_blind.held_out_error(result.cameras, pts2d)
    held_px = float(np.nanmedian(held)) if np.isfinite(held).any() else float("nan")
    return float(error / unit), held_px, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200, help="synthetic frames")
    frames = parser.parse_args().frames
    logging.disable(logging.WARNING)
    datasets = {**real_datasets(), **synthetic_datasets(frames)}
    score(synthetic_datasets(20)["rough rig"], LEGS)  # JIT, outside the timings
    print(f"| points_to_use | {' | '.join(datasets)} |")
    print(f"|---|{'---|' * len(datasets)}")
    default = Config.default().bundle_adjustment.points_to_use
    for label, points in CANDIDATES.items():
        label += " *" if points is not False and default == (points and tuple(points)) else ""
        cells = []
        for dataset in datasets.values():
            error, held, seconds = score(dataset, points)
            held_text = "n/a" if np.isnan(held) else f"{held:.2f} px"
            cells.append(f"{error:.3f} bones, {held_text}, {seconds:.1f} s")
        print(f"| {label} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
