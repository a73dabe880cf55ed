"""Session calibration (issue 38): one solve over a session's trials against one solve
per trial.

A synthetic session: ``--trials`` trials (default 10) of ``--frames`` frames (default
200) each, filmed by one rig, a tethered fly whose legs move little (a few percent of
a bone per frame; each trial its own movements and detector noise), the DeepFly3D-like
rig of ``tests/rough_rig.py`` (focal ~16,000 px at ~116 units) as the truth and its
rough starting rig (4 deg orbit, 4 % distance, 0.1 deg aim) as the start, 1 px noise
and 5 % gross outliers. Two visibility patterns, both real (``tests/front_blind.py``;
needs ``../shared/data``):

- ``sample``: the DeepFly3D sample's (front camera blind, each side camera its own
  side: the two sides share no view);
- ``package``: the DeepFly3D package example's (the front camera sees both sides).

For each, the default config's bundle adjustment runs once per trial (what the
workflow does without ``bundle_adjustment.session``; each trial's rig used for its own
3D) and once over the session (``max_frames`` shared between the trials; its rig used
for every trial), JIT warmed first. Printed side by side: the rig error against the
truth (camera centres after the best similarity, in % of the camera distance, and
camera orientation in degrees after it; mean over trials for the per-trial rigs), the
3D error of every trial's frames triangulated with its rig (median bones after a
similarity alignment, median over trials), the held-out-view error the session
summary reports (median px), and the solve times (sum over trials vs the one session
solve).

Run: ``.venv/bin/python benchmarks/session_calibration.py`` (about 5 minutes on the
shared 2-core machine at load 10; ``--frames 20``, short trials, about 2 minutes).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def rig_error(estimate, truth) -> tuple[float, float]:
    """Camera centres after the best similarity onto the truth's (% of the mean camera
    distance) and the cameras' orientation error after its rotation (mean degrees)."""
    import cv2

    from flylib.alignment import similarity_transform

    def poses(rig):
        rot = [cv2.Rodrigues(np.asarray(r, float))[0] for r in rig.rvecs]
        centres = np.array([-r.T @ np.asarray(t, float) for r, t in zip(rot, rig.tvecs)])
        return rot, centres

    rot_e, cen_e = poses(estimate)
    rot_t, cen_t = poses(truth)
    scale, rotation, shift = similarity_transform(cen_e, cen_t)
    moved = scale * cen_e @ rotation.T + shift
    distance = float(np.mean(np.linalg.norm(cen_t, axis=1)))
    position = float(np.mean(np.linalg.norm(moved - cen_t, axis=1)) / distance * 100)
    angles = []
    for re, rt in zip(rot_e, rot_t):
        # a world point x maps to re @ x; in the truth's frame x = R^T (y - t) / s
        delta = rt @ (re @ rotation.T).T
        angles.append(np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1))))
    return position, float(np.mean(angles))


def make_session(visibility: np.ndarray, trials: int, frames: int):
    """``(true rig, rough start, [(truth, pts2d, conf), ...])``."""
    import rough_rig as rr

    rig = rr.true_rig(seed=0)
    start = rr.rough_start(rig, seed=1)
    out = []
    for k in range(trials):
        truth = rr.tethered_fly(frames, seed=10 + k)
        rng = np.random.default_rng(1000 + k)
        pts2d, conf, _ = rr.detections(rig, truth, visibility, rng, 1.0, 0.05, 80.0)
        out.append((truth, pts2d, conf))
    return rig, start, out


def evaluate(rig, trial, truth_rig) -> dict:
    """3D error (median bones) and held-out-view error (median px) of one trial with ``rig``."""
    import front_blind

    from flylib.config import Config
    from flylib.triangulation import reconstruct

    import rough_rig as rr

    truth, pts2d, conf = trial
    pts3d, _, _ = reconstruct(rig, pts2d, Config.default().triangulation, conf)
    error = rr.similarity_error(pts3d, truth) / rr.median_bone(truth)
    held = front_blind.held_out_error(rig, pts2d)
    return {"3d": float(np.nanmedian(error)), "held_out": float(np.nanmedian(held))}


def run_case(name: str, visibility: np.ndarray, trials: int, frames: int) -> dict:
    from flylib.config import Config
    from flylib.pipeline.bundle_adjustment import compute_bundle_adjustment
    from flylib.pipeline.session_calibration import (
        SessionCalibrationInputs,
        compute_session_calibration,
    )

    config = Config.default()
    truth_rig, start, session = make_session(visibility, trials, frames)
    per_trial = SessionCalibrationInputs.from_config(config)  # same table, session aside
    began = time.perf_counter()
    trial_rigs = [
        compute_bundle_adjustment(per_trial, start, pts2d, conf).cameras
        for _, pts2d, conf in session
    ]
    trial_seconds = time.perf_counter() - began
    began = time.perf_counter()
    solved, frames_used = compute_session_calibration(
        per_trial, start, [s[1] for s in session], [s[2] for s in session]
    )
    session_seconds = time.perf_counter() - began
    rows = {
        "start": {
            "rig": rig_error(start, truth_rig),
            "eval": [evaluate(start, t, truth_rig) for t in session],
        },
        "per-trial": {
            "rig": tuple(np.mean([rig_error(r, truth_rig) for r in trial_rigs], axis=0)),
            "eval": [evaluate(r, t, truth_rig) for r, t in zip(trial_rigs, session)],
            "seconds": trial_seconds,
        },
        "session": {
            "rig": rig_error(solved.cameras, truth_rig),
            "eval": [evaluate(solved.cameras, t, truth_rig) for t in session],
            "seconds": session_seconds,
        },
    }
    print(
        f"\n{name}: {trials} trials x {frames} frames, session solve over "
        f"{sum(f.size for f in frames_used)} frames ({frames_used[0].size} per trial)"
    )
    print(
        f"  {'rig':10s} {'centres %':>10s} {'aim deg':>8s} {'3D bones':>9s} "
        f"{'worst trial':>11s} {'held-out px':>11s} {'solve s':>8s}"
    )
    for label, row in rows.items():
        errors = [e["3d"] for e in row["eval"]]
        held = [e["held_out"] for e in row["eval"]]
        seconds = f"{row['seconds']:8.1f}" if "seconds" in row else f"{'-':>8s}"
        print(
            f"  {label:10s} {row['rig'][0]:10.3f} {row['rig'][1]:8.3f} "
            f"{np.median(errors):9.4f} {np.max(errors):11.4f} {np.median(held):11.3f} {seconds}"
        )
    ratio = rows["per-trial"]["seconds"] / max(rows["session"]["seconds"], 1e-9)
    print(f"  per-trial solves / session solve: {ratio:.1f}x the time")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--frames", type=int, default=200, help="frames per trial")
    parser.add_argument("--case", choices=("sample", "package", "both"), default="both")
    args = parser.parse_args()
    import front_blind

    if not front_blind.available():
        print(f"skipped: {front_blind.PACKAGE_EXAMPLE} or the DeepFly3D sample is absent")
        return
    logging.disable(logging.WARNING)  # the poorly-determined-rig warning, once per solve
    warnings.simplefilter("ignore")
    from flylib.config import Config
    from flylib.pipeline.bundle_adjustment import compute_bundle_adjustment
    from flylib.pipeline.inputs import stage_inputs

    # JIT warm-up on a tiny problem, so neither side pays the compilation
    _, start, warm = make_session(front_blind.sample_visibility(), 1, 20)
    compute_bundle_adjustment(
        stage_inputs(Config.default(), "bundle_adjustment"), start, warm[0][1], warm[0][2]
    )
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    cases = {"sample": front_blind.sample_visibility, "package": front_blind.package_visibility}
    for name, visibility in cases.items():
        if args.case in (name, "both"):
            label = {
                "sample": "DeepFly3D sample visibility (front camera blind)",
                "package": "package example visibility (front camera sees both sides)",
            }[name]
            run_case(label, visibility(), args.trials, args.frames)


if __name__ == "__main__":
    main()
