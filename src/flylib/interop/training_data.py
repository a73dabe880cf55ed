"""Corrected frames as labeled training data, in DeepLabCut's labeled-data layout.

A person's corrections (``flylib gui``, saved, applied by the next workflow run) are the
first step to fine-tuning a detector on a lab's own footage. For every frame in which a
point was corrected, every view's frame is written as a PNG with its labels::

    <directory>/labeled-data/<video stem>/img0007.png
    <directory>/labeled-data/<video stem>/CollectedData_<scorer>.csv
    <directory>/labeled-data/<video stem>/CollectedData_<scorer>.h5

the layout DeepLabCut's ``create_training_dataset`` reads from a project's
``labeled-data`` folder (one folder per video, named after the video's stem, rows
indexed ``("labeled-data", <video stem>, "img0007.png")``, columns
``(scorer, bodyparts, coords)``, the ``.h5`` a pandas frame under key
``df_with_missing``); ``sleap_io.load_dlc`` reads the CSV too.

The label of a point in a view is, in this order: empty (NaN) where a person marked it
invisible; the 2D the corrected 3D was solved from (the person's edit, or a detection
the robust triangulation kept); the reprojection of the corrected 3D where the detector
saw the point in that view but the triangulation left the detection out (a detection
error, the corrected geometry's answer); empty otherwise (the view does not see it).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import FootageError, ResultsError
from ..paths import atomic_path

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

__all__ = ["export_training_data", "training_labels"]

log = logging.getLogger(__name__)

DLC_H5_KEY = "df_with_missing"


def training_labels(
    used2d: Float[np.ndarray, "V T P 2"],
    given2d: Float[np.ndarray, "V T P 2"],
    reprojected: Float[np.ndarray, "V T P 2"],
    touched: Bool[np.ndarray, "V T P"],
    image_sizes: list[tuple[int, int]],
) -> Float[np.ndarray, "V T P 2"]:
    """The training label of every (view, frame, point) (see the module's docstring).

    Parameters
    ----------
    used2d
        ``(V, T, P, 2)`` the 2D the 3D was solved from (corrections applied), NaN = left out.
    given2d
        ``(V, T, P, 2)`` the 2D the triangulation was given (the detector's), NaN = none.
    reprojected
        ``(V, T, P, 2)`` the corrected 3D projected into each view, NaN without 3D.
    touched
        ``(V, T, P)`` bool: a person edited the point in that view or marked it invisible.
    image_sizes
        ``(height, width)`` per view: a reprojection outside the frame is no label.

    Returns
    -------
    np.ndarray
        ``(V, T, P, 2)`` float64 pixels, NaN = no label.
    """
    used = np.asarray(used2d, dtype=np.float64)
    has_used = np.isfinite(used).all(-1)
    seen = np.isfinite(np.asarray(given2d, dtype=np.float64)).all(-1)
    ghost = np.asarray(reprojected, dtype=np.float64)
    size = np.array([[w, h] for h, w in image_sizes], dtype=np.float64)[:, None, None, :]
    inside = np.isfinite(ghost).all(-1) & ((ghost >= 0) & (ghost <= size - 1)).all(-1)
    from_ghost = ~has_used & seen & inside & ~np.asarray(touched, bool)
    labels = np.where(has_used[..., None], used, np.nan)
    labels = np.where(from_ghost[..., None], ghost, labels)
    invisible = np.asarray(touched, bool) & ~has_used
    return np.where(invisible[..., None], np.nan, labels)


def _dlc_frame(labels: np.ndarray, folder: str, images: list[str], points: list[str], scorer: str):
    """One video's labels as DeepLabCut's CollectedData frame: ``(F, P * 2)``."""
    import pandas as pd

    columns = pd.MultiIndex.from_product(
        [[scorer], points, ["x", "y"]], names=["scorer", "bodyparts", "coords"]
    )
    index = pd.MultiIndex.from_tuples([("labeled-data", folder, name) for name in images])
    return pd.DataFrame(labels.reshape(len(images), -1), index=index, columns=columns)


def export_training_data(
    results: str | Path,
    directory: str | Path,
    *,
    config: Any = None,
    recording: str | Path | None = None,
    scorer: str = "flylib",
) -> list[Path]:
    """Write the corrected frames of a ``results.h5`` as DeepLabCut labeled data.

    Parameters
    ----------
    results
        A ``results.h5`` computed with a corrections sidecar (the workflow run after a
        save in ``flylib gui``).
    directory
        A DeepLabCut project folder (or any folder): ``labeled-data/`` is made in it.
    config
        The run's config; default the snapshot beside ``results.h5``, else flylib's default.
    recording
        The recording directory (its footage); default the one ``results.h5`` names.
    scorer
        DeepLabCut's scorer name (``CollectedData_<scorer>``; a DLC project's ``scorer``).

    Returns
    -------
    list of Path
        The files written (per view: the PNGs, then the CSV and the ``.h5``).

    Raises
    ------
    ResultsError
        When the result holds no corrected frame.
    FootageError
        When a view's footage is not found or a frame cannot be read.
    """
    import cv2

    from ..config import Config
    from ..config.sources import footage_globs
    from ..io import open_reader
    from ..results import PoseResult, open_checked
    from .views import footage_files

    results = Path(results)
    result = PoseResult.load(results)
    with open_checked(results) as f:
        if "triangulation/corrected" not in f or result.pts3d is None:
            raise ResultsError(
                f"{results}: holds no corrections; correct frames in `flylib gui {results}`, "
                "save, run snakemake, then export the training data"
            )
        corrected = np.asarray(f["triangulation/corrected"][()], bool)
        touched = np.asarray(f["triangulation/corrected_2d"][()], bool)
        source = "pictorial_structures" if "pictorial_structures/points" in f else "pose2d"
        given = np.asarray(f[f"{source}/points"][()], dtype=np.float64)
    frames = np.flatnonzero(corrected.any(axis=1) | touched.any(axis=(0, 2)))
    if not len(frames):
        raise ResultsError(
            f"{results}: no frame was corrected; correct frames in `flylib gui {results}`, "
            "save, run snakemake, then export the training data"
        )
    if config is None:
        config = Config.of_outputs(results.parent)
    recording = Path(recording) if recording else Path(result.meta.get("recording") or "")
    views = list(result.cameras.names)
    footage = footage_files(footage_globs(config), recording) if recording.is_dir() else {}
    missing = [v for v in views if not footage.get(v)]
    if missing:
        raise FootageError(
            f"{recording}: no footage of view(s) {', '.join(missing)} for the training images; "
            "pass the recording directory (--recording DIR)"
        )
    sizes = [tuple((result.image_sizes or {}).get(v, (0, 0))) for v in views]
    reprojected = result.cameras.project(result.pts3d[frames])  # (V, F, P, 2)
    readers = {v: open_reader(footage[v]) for v in views}
    if not all(sizes[i][0] for i in range(len(views))):
        sizes = [readers[v].frame_size() for v in views]
    labels = training_labels(
        result.pts2d[:, frames], given[:, frames], reprojected, touched[:, frames], sizes
    )
    points = [str(p) for p in result.skeleton.point_names]
    digits = max(4, len(str(result.n_frames - 1)))
    written: list[Path] = []
    for v, view in enumerate(views):
        files = footage[view]
        folder = files[0].stem if len(files) == 1 else view
        out = Path(directory) / "labeled-data" / folder
        out.mkdir(parents=True, exist_ok=True)
        images = [f"img{int(t):0{digits}d}.png" for t in frames]
        try:
            pixels = readers[view][[int(t) for t in frames]]
        except (FootageError, OSError, ValueError, IndexError) as exc:
            raise FootageError(f"{files[0]}: cannot read the corrected frames ({exc})") from None
        for name, rgb in zip(images, pixels):
            with atomic_path(out / name) as tmp:
                ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
                if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
                    raise FootageError(f"{files[0]}: PNG encoding failed")
                tmp.write_bytes(data.tobytes())
            written.append(out / name)
        table = _dlc_frame(labels[v], folder, images, points, scorer)
        csv_path, h5_path = out / f"CollectedData_{scorer}.csv", out / f"CollectedData_{scorer}.h5"
        with atomic_path(csv_path) as tmp:
            table.to_csv(tmp)
        with atomic_path(h5_path) as tmp:
            table.to_hdf(tmp, key=DLC_H5_KEY, mode="w")
        written += [csv_path, h5_path]
    log.info(
        "training data: %d corrected frames x %d views in %s/labeled-data",
        len(frames),
        len(views),
        directory,
    )
    return written
