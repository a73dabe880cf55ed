"""Fewer cameras on real data: DeepFly3D's packaged example, with and without bundle adjustment.

DeepFly3D 1.x's example result (``../shared/data/deepfly3d-package-example``: its 2D in
pixels and its own 3D, the reference) is reconstructed by :func:`flylib.run_from_points2d` on
a subset of the default config's rig (7, 6, 5 and 4 cameras), without and with bundle
adjustment. Printed per subset: the 3D error after the best similarity (or mirrored
similarity: the default rig explains DeepFly3D's images with the mirror-image world) in
median bone lengths of DeepFly3D's 3D (the skeleton's bones), the held-out-view error (median px) of the rig used, what
bundle adjustment decided and its warnings.

``--workflow`` measures the same table through the workflow instead, as a user runs it: for
each subset and with and without bundle adjustment, a ``my.yaml`` merged over the default
config (the example's ``df3d_result.pkl`` imported with ``pose2d.import``, its frame size
given, the cameras left out removed with ``cameras: {x: null}``, no visualisation: there is
no footage), run with ``snakemake --configfile my.yaml``. Printed per run: the 3D error of
``results.h5`` (the refined output) and of the triangulation's 3D, in median bones as above,
and the held-out-view error the run reports (median px, its ``summary.json``: the
triangulation's and the refined output's).

The workflow's import keeps, per camera, only the points the default detection plan gives
that camera (the front camera's leg bases and the side cameras' far abdomen are dropped,
with a warning), as the detector would; the library mode triangulates every 2D point of
the pickle. ``--all-points`` adds ``pose2d.import.view_points: all`` (the pickle's every
point, as the library mode) to tell the two effects apart.

Run: ``PYTHONPATH=src python benchmarks/fewer_cameras.py [--workflow [--all-points]]``
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from front_blind import (  # noqa: E402
    PACKAGE_EXAMPLE,
    default_start,
    held_out_error,
    mirror_free_error,
    package_points2d,
    recorded_poses,
)

from flylib import run_from_points2d  # noqa: E402
from flylib.skeleton import Skeleton  # noqa: E402

from rig_constants import VIEWS  # noqa: E402

#: the subsets of the issue's table (issue 46)
SUBSETS = {
    7: VIEWS,
    6: ("rh", "rm", "rf", "lf", "lm", "lh"),
    5: ("rh", "rf", "f", "lf", "lh"),
    4: ("rh", "rf", "lf", "lh"),
}


def reconstruct(views, bundle_adjust: bool):
    """``(result, error in bones, warnings)`` of the subset ``views``."""
    pts2d = package_points2d()[[VIEWS.index(v) for v in views]]
    truth = recorded_poses()
    rig = default_start().subset(views)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run_from_points2d(rig, Skeleton.fly(), pts2d, do_bundle_adjust=bundle_adjust)
    err = mirror_free_error(np.asarray(result.pts3d, float), truth)
    messages = [str(w.message) for w in caught if "bundle adjustment" in str(w.message)]
    bones = np.asarray(Skeleton.fly().bones, int)
    unit = np.nanmedian(np.linalg.norm(truth[:, bones[:, 0]] - truth[:, bones[:, 1]], axis=-1))
    return result, float(np.nanmedian(err)) / unit, messages


def workflow_run(root: Path, views, bundle_adjust: bool, all_points: bool = False) -> dict:
    """Run the workflow on the package example with the cameras ``views`` (the rest removed
    in ``my.yaml``); ``{name: figure}`` of the run."""
    import h5py
    import yaml

    from flylib.results import PoseResult

    name = f"{len(views)}cams_{'ba' if bundle_adjust else 'noba'}"
    work = root / name
    work.mkdir(parents=True)
    mine = {
        "recordings": [
            {
                "path": str(PACKAGE_EXAMPLE),
                "import": {
                    "format": "deepfly3d",
                    "files": "df3d_result.pkl",
                    "image_size": [480, 960],
                    # the pickle's cameras in order; null: a camera removed below
                    "views": [v if v in views else None for v in VIEWS],
                    **({"view_points": "all"} if all_points else {}),
                },
            }
        ],
        "outdir": str(work / "out" / "{id}"),
        "cameras": {v: None for v in VIEWS if v not in views},
        "pipeline": {"do_bundle_adjustment": bundle_adjust, "do_visualization": False},
        "kinematics": {"allow_mirrored": True},  # the 3D is compared mirror-free below
    }
    (work / "my.yaml").write_text(yaml.safe_dump(mine, sort_keys=False))
    cmd = [str(Path(sys.executable).with_name("snakemake")), "-s", str(REPO / "Snakefile")]
    cmd += ["--configfile", "my.yaml", "--cores", "2"]
    proc = subprocess.run(cmd, cwd=work, capture_output=True, text=True, check=False)
    (work / "run.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        return {"failed": f"rc {proc.returncode}, see {work / 'run.log'}"}
    outdir = work / "out" / PACKAGE_EXAMPLE.name
    truth = recorded_poses()
    bones = np.asarray(Skeleton.fly().bones, int)
    unit = np.nanmedian(np.linalg.norm(truth[:, bones[:, 0]] - truth[:, bones[:, 1]], axis=-1))
    out = {}
    with h5py.File(outdir / "stages" / "triangulation.h5", "r") as f:
        triangulated = f["triangulation/points3d"][()]
    for label, pts3d in (
        ("output", PoseResult.load(outdir / "results.h5").pts3d),
        ("triangulation", triangulated),
    ):
        err = mirror_free_error(np.asarray(pts3d, float), truth)
        out[label] = float(np.nanmedian(err)) / unit
    accuracy = json.loads((outdir / "summary.json").read_text())["accuracy"]
    out["held_out"] = accuracy["output"]["held_out_px"]["median"]
    tail = proc.stderr[proc.stderr.rfind("flylib: per-recording results") :]
    out["notes"] = [line.strip() for line in tail.splitlines() if "bundle adjustment" in line]
    return out


def main_workflow(all_points: bool) -> None:
    logging.disable(logging.WARNING)
    root = Path(tempfile.mkdtemp(prefix="fewer_cameras_"))
    print(f"(runs in {root})")
    print("| cameras | 3D, no BA | 3D, BA | held-out px, no BA | held-out px, BA |")
    print("|---|---|---|---|---|")
    notes = []
    for n, views in SUBSETS.items():
        runs = [workflow_run(root, views, ba, all_points) for ba in (False, True)]
        cells = [r.get("failed") or f"{r['output']:.3f} ({r['triangulation']:.3f})" for r in runs]
        cells += [f"{r['held_out']:.1f}" if r.get("held_out") else "n/a" for r in runs]
        print(f"| {n} ({', '.join(views)}) | " + " | ".join(cells) + " |", flush=True)
        notes += [f"{n} cameras, BA: {m}" for m in runs[1].get("notes", [])]
    print("3D: results.h5 (the triangulation's 3D in brackets), median bones; held-out: the")
    print("output's, median px (summary.json)")
    for note in notes:
        print(f"- {note}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--workflow", action="store_true", help="through snakemake, as a user runs it"
    )
    parser.add_argument(
        "--all-points",
        action="store_true",
        help="with --workflow: keep every 2D point of the pickle (pose2d.import.view_points: all)",
    )
    args = parser.parse_args()
    if args.workflow:
        return main_workflow(args.all_points)
    logging.disable(logging.WARNING)  # the warnings are printed below the table
    if not (PACKAGE_EXAMPLE / "df3d_result.pkl").is_file():
        sys.exit(f"needs {PACKAGE_EXAMPLE} (../shared/data)")
    print("| cameras | no bundle adjustment | with bundle adjustment | held-out px (start -> BA) |")
    print("|---|---|---|---|")
    notes = []
    for n, views in SUBSETS.items():
        plain, e0, _ = reconstruct(views, False)
        adjusted, e1, messages = reconstruct(views, True)
        pts2d = package_points2d()[[VIEWS.index(v) for v in views]]
        held = [held_out_error(r.cameras, pts2d) for r in (plain, adjusted)]
        h0, h1 = (f"{np.nanmedian(h):.1f}" if np.isfinite(h).any() else "n/a" for h in held)
        print(f"| {n} ({', '.join(views)}) | {e0:.3f} | {e1:.3f} | {h0} -> {h1} |")
        notes += [f"{n} cameras: {m}" for m in messages]
    for note in notes:
        print(f"- {note}")


if __name__ == "__main__":
    main()
