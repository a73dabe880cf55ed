"""The per-stage, per-point and per-bone figures of a ``results.h5`` (what ``flylib inspect``
prints): :func:`summarize_results`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ResultsError
from ..handedness import handedness as judge
from ..stages import FINAL_3D, SOLVES_3D
from .datasets import read_json_attrs, read_strings
from .groups import skeleton_from_group
from .hdf5 import open_checked, read_meta_from

__all__ = ["summarize_results"]


def _percentile(values: np.ndarray, q: float) -> float:
    finite = values[np.isfinite(values)]
    return float(np.percentile(finite, q)) if finite.size else float("nan")


def _held_out(accuracy: dict, stage: str) -> dict:
    """Held-out figures of a 3D stage's accuracy attrs: refinement's output, else triangulation."""
    return accuracy["output" if stage == "refinement" else "triangulation"]


def summarize_results(path: Path) -> dict:
    """``{"meta", "handedness", "stages": [row...], "points": [row...], "bones": [row...],
    "stage_3d", "accuracy", "session"}``; rows are dicts of plain numbers and strings. Reprojection
    errors are in pixels; the bone spread is the interquartile range of the bone's length over frames
    divided by its median (0 for a rigid bone)."""
    with open_checked(path, "pass the results.h5 a run wrote") as f:
        meta = read_meta_from(f)
        if "skeleton/point_names" not in f:
            raise ResultsError(f"{path}: no skeleton/point_names; not a flylib results file")
        names = read_strings(f["skeleton/point_names"])
        skeleton = skeleton_from_group(f["skeleton"])
        bones = np.zeros((0, 2), int)
        if "skeleton/bones" in f:
            bones = np.asarray(f["skeleton/bones"][()], dtype=int).reshape(-1, 2)
        stages = []
        for stage in ("pose2d", "bundle_adjustment", *SOLVES_3D):
            if stage not in f:
                continue
            row: dict = {"stage": stage}
            group = f[stage]
            if "points" in group:
                pts2d = group["points"][()]
                row["views"], row["frames"] = int(pts2d.shape[0]), int(pts2d.shape[1])
                row["observed_2d"] = float(np.isfinite(pts2d).all(-1).mean())
            if "points3d" in group:
                pts3d = group["points3d"][()]
                row["frames"] = int(pts3d.shape[0])
                row["reconstructed"] = float(np.isfinite(pts3d).all(-1).mean())
            if "reproj_error" in group:
                err = group["reproj_error"][()]
                row["err_median"], row["err_p95"] = _percentile(err, 50), _percentile(err, 95)
            if "cameras/names" in group:
                row["cameras"] = len(read_strings(group["cameras/names"]))
            accuracy = read_json_attrs(group).get("accuracy")
            if isinstance(accuracy, dict):
                row["accuracy"] = accuracy
                held = _held_out(accuracy, stage)["held_out_px"]
                row["held_median"], row["held_p95"] = held["median"], held["p95"]
            stages.append(row)
        rig = read_meta_from(f["bundle_adjustment"]) if "bundle_adjustment" in f else {}
        stage_3d = next((s for s in FINAL_3D if f"{s}/points3d" in f), None)
        source_2d = next((s for s in (*FINAL_3D, "pose2d") if f"{s}/points" in f), None)
        pts2d = f[f"{source_2d}/points"][()] if source_2d else None
        pts3d = f[f"{stage_3d}/points3d"][()] if stage_3d else None
        err = (
            f[f"{stage_3d}/reproj_error"][()]
            if stage_3d and f"{stage_3d}/reproj_error" in f
            else None
        )

    accuracy = next(
        (s["accuracy"] for s in stages if s["stage"] == stage_3d and "accuracy" in s), None
    )
    held_points = {} if accuracy is None else _held_out(accuracy, stage_3d)["per_point"]
    points = []
    for p, name in enumerate(names):
        row = {"point": name}
        if name in held_points:
            row["held_median"] = held_points[name]["median"]
            row["held_p95"] = held_points[name]["p95"]
        if pts2d is not None:
            row["views_observing"] = float(np.isfinite(pts2d[:, :, p]).all(-1).sum(0).mean())
        if pts3d is not None:
            row["reconstructed"] = float(np.isfinite(pts3d[:, p]).all(-1).mean())
        if err is not None:
            row["err_median"] = _percentile(err[:, :, p], 50)
            row["err_p95"] = _percentile(err[:, :, p], 95)
        points.append(row)
    bone_rows = []
    if pts3d is not None:
        for a, b in bones:
            length = np.linalg.norm(pts3d[:, a] - pts3d[:, b], axis=-1)
            median = _percentile(length, 50)
            iqr = _percentile(length, 75) - _percentile(length, 25)
            bone_rows.append(
                {
                    "bone": f"{names[a]}-{names[b]}",
                    "frames": int(np.isfinite(length).sum()),
                    "median_length": median,
                    "spread": iqr / median if median > 0 else float("nan"),
                }
            )
    handedness = meta.get("handedness")
    if not isinstance(handedness, dict) and pts3d is not None:  # assembled by an older flylib
        handedness = judge(np.asarray(pts3d, float), skeleton).as_dict()
    return {
        "meta": meta,
        "handedness": handedness,
        "stages": stages,
        "points": points,
        "bones": bone_rows,
        "stage_3d": stage_3d,
        "accuracy": accuracy,
        # the session whose rig the results use ({name, members}) and the folder it was solved in
        "session": rig.get("session")
        and {**rig["session"], "folder": rig.get("writer", {}).get("outdir")},
    }
