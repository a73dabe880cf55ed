"""Exports for other tools: Anipose's 3D CSV and per-view DeepLabCut CSVs.

3D CSV, exactly Anipose's ``pose-3d`` layout (as ``movement`` and Anipose read it): per frame a row;
per skeleton point, in skeleton order,
``<point>_x``, ``_y``, ``_z`` (world units), ``_error`` (mean reprojection error in pixels over the
views the point rests on), ``_ncams`` (how many views' 2D observations it rests on) and ``_score``
(the lowest 2D confidence among those views); then the alignment ``M_00`` ... ``M_22`` (the rotation
applied to the points, row-major) and ``center_0..2`` (the offset subtracted after it), and last
``fnum`` (the frame number, from 0). flylib applies no alignment, so ``M`` is the identity and
``center`` zero. As in Anipose, a point resting on fewer than two views has NaN ``_error``,
``_ncams`` and ``_score``, and an unreconstructed point NaN coordinates.

2D: one ``<view>.csv`` per view in the DeepLabCut layout, the skeleton point names as body parts and
the detection confidence as ``likelihood``: the detections (``pose2d/points``, what the detector or
the import gave) with the manual corrections applied (:func:`flylib.results.read_detections`), never
the subset a 3D stage kept; a missing point has empty ``x``, ``y`` and ``likelihood``. These import
back as the same 2D with ``pose2d.import: {format: dlc_csv}`` (default ``files: "{view}.csv"``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from ..errors import ResultsError
from ..paths import atomic_path
from .dlc import write_dlc_csv

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float


def points3d_table(
    pts3d: Float[np.ndarray, "T P 3"],
    point_names: list[str],
    reproj_error: Float[np.ndarray, "V T P"] | None = None,
    pts2d: Float[np.ndarray, "V T P 2"] | None = None,
    conf: Float[np.ndarray, "V T P"] | None = None,
) -> pd.DataFrame:
    """The per-frame 3D table in Anipose's ``pose-3d`` CSV layout (module docstring).

    Without ``reproj_error`` ``_error`` is NaN; without ``pts2d`` (the 2D the 3D rests on)
    ``_ncams`` counts views with a finite error; without ``conf`` each observation scores 1."""
    pts3d = np.asarray(pts3d, dtype=np.float64)
    n_frames, n_points, _ = pts3d.shape
    if len(point_names) != n_points:
        raise ValueError(f"{len(point_names)} point names for {n_points} points")
    reconstructed = np.isfinite(pts3d).all(-1)
    if pts2d is not None:
        used = np.isfinite(np.asarray(pts2d, dtype=np.float64)).all(-1)  # (V, T, P)
    elif reproj_error is not None:
        used = np.isfinite(np.asarray(reproj_error, dtype=np.float64))
    else:
        used = np.zeros((0, n_frames, n_points), dtype=bool)
    ncams = used.sum(0).astype(np.float64)
    if reproj_error is not None:
        err = np.asarray(reproj_error, dtype=np.float64)
        counts = np.isfinite(err).sum(0)
        with np.errstate(invalid="ignore", divide="ignore"):
            error = np.where(counts > 0, np.nansum(err, 0) / np.maximum(counts, 1), np.nan)
    else:
        error = np.full((n_frames, n_points), np.nan)
    scores = np.ones(used.shape) if conf is None else np.asarray(conf, dtype=np.float64)
    # Anipose: the lowest score among the views used (unused views count as 2, above any score).
    score = (
        np.where(used, np.nan_to_num(scores, nan=0.0), 2.0).min(0)
        if used.size
        else np.full((n_frames, n_points), np.nan)
    )
    # Anipose blanks error, score and camera count below two views.
    too_few = (ncams < 2) | ~reconstructed
    error = np.where(too_few, np.nan, error)
    score = np.where(too_few, np.nan, score)
    ncams = np.where(ncams < 2, np.nan, ncams)
    columns: dict[str, np.ndarray] = {}
    for p, name in enumerate(point_names):
        for c, axis in enumerate("xyz"):
            columns[f"{name}_{axis}"] = pts3d[:, p, c]
        columns[f"{name}_error"] = error[:, p]
        columns[f"{name}_ncams"] = ncams[:, p]
        columns[f"{name}_score"] = score[:, p]
    rotation, center = np.eye(3), np.zeros(3)  # flylib applies no alignment
    for i in range(3):
        for j in range(3):
            columns[f"M_{i}{j}"] = np.full(n_frames, rotation[i, j])
    for i in range(3):
        columns[f"center_{i}"] = np.full(n_frames, center[i])
    columns["fnum"] = np.arange(n_frames)
    return pd.DataFrame(columns)


def write_points3d_csv(
    path: Path,
    pts3d: Float[np.ndarray, "T P 3"],
    point_names: list[str],
    reproj_error: Float[np.ndarray, "V T P"] | None = None,
    pts2d: Float[np.ndarray, "V T P 2"] | None = None,
    conf: Float[np.ndarray, "V T P"] | None = None,
) -> Path:
    """Write :func:`points3d_table` to ``path`` as CSV (atomically); returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        points3d_table(pts3d, point_names, reproj_error, pts2d, conf).to_csv(tmp, index=False)
    return path


def write_dlc_views(
    directory: Path,
    pts2d: Float[np.ndarray, "V T P 2"],
    conf: Float[np.ndarray, "V T P"] | None,
    view_names: list[str],
    point_names: list[str],
    scorer: str = "flylib",
) -> list[Path]:
    """Write one DeepLabCut CSV per view, ``<directory>/<view>.csv`` (the folder is created), from
    ``pts2d`` ``(V, T, P, 2)`` pixels (NaN = missing) and ``conf`` ``(V, T, P)`` (``None``: 1 where
    present); returns the files in view order."""
    pts2d = np.asarray(pts2d, dtype=np.float64)
    if len(view_names) != pts2d.shape[0]:
        raise ValueError(f"{len(view_names)} view names for {pts2d.shape[0]} views")
    directory = Path(directory)
    return [
        write_dlc_csv(
            directory / f"{view}.csv",
            pts2d[v],
            None if conf is None else np.asarray(conf, dtype=np.float64)[v],
            list(point_names),
            scorer,
        )
        for v, view in enumerate(view_names)
    ]


def export_result(
    result,
    csv3d: Path | None = None,
    dlc_dir: Path | None = None,
    detections=None,
) -> list[Path]:
    """Export a :class:`flylib.results.PoseResult`: the Anipose 3D CSV ``csv3d`` and/or per-view DLC
    CSVs of ``detections`` (:func:`flylib.results.read_detections`, required) in ``dlc_dir``
    (``None``: not written); returns the files written."""
    if dlc_dir is not None and detections is None:
        raise ValueError("export_result: the DLC CSVs need the detections (read_detections)")
    written: list[Path] = []
    names = list(result.skeleton.point_names)
    if csv3d is not None:
        if result.pts3d is None:
            raise ResultsError(
                "the results file has no 3D points (no triangulation or pictorial_structures "
                "group); enable a 3D stage and re-run, or export only the 2D CSVs"
            )
        written.append(
            write_points3d_csv(
                csv3d, result.pts3d, names, result.reproj_error, result.pts2d, result.conf
            )
        )
    if dlc_dir is not None:
        written += write_dlc_views(
            dlc_dir, detections.points, detections.conf, list(result.cameras.names), names
        )
    return written
