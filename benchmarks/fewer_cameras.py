"""Fewer cameras on real data: DeepFly3D's packaged example, with and without bundle adjustment.

DeepFly3D 1.x's example result (``../shared/data/deepfly3d-package-example``: its 2D in
pixels and its own 3D, the reference) is reconstructed by :func:`flylib.run_from_points2d` on
a subset of the default config's rig (7, 6, 5 and 4 cameras), without and with bundle
adjustment. Printed per subset: the 3D error after the best similarity (or mirrored
similarity: the default rig explains DeepFly3D's images with the mirror-image world) in
median bone lengths of DeepFly3D's 3D (the skeleton's bones), the held-out-view error (median px) of the rig used, what
bundle adjustment decided and its warnings.

Run: ``PYTHONPATH=src python benchmarks/fewer_cameras.py``
"""

from __future__ import annotations

import logging
import sys
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


def main() -> None:
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
