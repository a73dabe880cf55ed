"""Corrected frames as labeled training data, in DeepLabCut's labeled-data layout.

For fine-tuning a detector on a lab's own footage: for every frame in which a point was corrected
(``flylib gui``, then a workflow run), every view's frame is written as a PNG with its labels::

    <directory>/labeled-data/<video stem>/img0007.png
    <directory>/labeled-data/<video stem>/CollectedData_<scorer>.csv
    <directory>/labeled-data/<video stem>/CollectedData_<scorer>.h5

as DeepLabCut's ``create_training_dataset`` reads it (rows ``("labeled-data", <video stem>,
"img0007.png")``, columns ``(scorer, bodyparts, coords)``, ``.h5`` key ``df_with_missing``).

A point's label in a view is, in this order: empty (NaN) where a person marked it invisible; the 2D
the corrected 3D was solved from (the person's edit, or a detection the robust triangulation kept);
the reprojection of the corrected 3D where the detector saw the point in that view but the
triangulation left the detection out (a detection error); empty otherwise.

Into an existing project the labels are merged row by row (:func:`merge_collected`): every other
label and image is kept, and each ``CollectedData`` file changed is first copied to
``<name>.<UTC time>.bak``."""

from __future__ import annotations

import csv
import itertools
import logging
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FootageError, OutputError, ResultsError
from ..paths import atomic_path, refuse_overwrite

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Bool, Float

__all__ = ["export_training_data", "merge_collected", "training_labels"]

log = logging.getLogger(__name__)

DLC_H5_KEY = "df_with_missing"


def training_labels(
    used2d: Float[np.ndarray, "V T P 2"],
    given2d: Float[np.ndarray, "V T P 2"],
    reprojected: Float[np.ndarray, "V T P 2"],
    touched: Bool[np.ndarray, "V T P"],
    image_sizes: list[tuple[int, int]],
) -> Float[np.ndarray, "V T P 2"]:
    """The training label of every (view, frame, point) (module docstring), NaN = no label.

    ``used2d``: the 2D the 3D was solved from (NaN = left out); ``given2d``: the detector's;
    ``touched``: a person edited the point in that view or marked it invisible. A reprojection
    outside the frame is no label."""
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


_HEADER_ROWS = ("scorer", "individuals", "bodyparts", "coords")


def read_collected_csv(path: Path):
    """A ``CollectedData_<scorer>.csv``, its header rows (with ``individuals`` or not) and index
    columns (3, or one path column in older projects) found from the file itself."""
    import pandas as pd

    with open(path, newline="", encoding="utf-8") as f:
        rows = list(itertools.islice(csv.reader(f), len(_HEADER_ROWS) + 1))
    headers = sum(1 for _ in itertools.takewhile(lambda r: r and r[0] in _HEADER_ROWS, rows))
    if not headers:
        raise OutputError(
            f"{path}: not a DeepLabCut CollectedData file (no scorer/bodyparts/coords header "
            "rows); move it away or export to another folder"
        )
    first = rows[0]
    index = 1 + sum(1 for _ in itertools.takewhile(lambda c: c == "", first[1:]))
    return pd.read_csv(path, header=list(range(headers)), index_col=list(range(index)))


@dataclass(frozen=True)
class MergeCount:
    """What :func:`merge_collected` did to one file's frames (rows)."""

    added: int
    updated: int
    kept: int

    @property
    def changed(self) -> bool:
        return bool(self.added or self.updated)


def merge_collected(existing, new, cleared: np.ndarray):
    """Merge flylib's labels ``new`` into a project's ``existing`` CollectedData frame; returns the
    merged frame (new body parts and frames appended) and a :class:`MergeCount`.

    Where ``cleared`` (bool, ``new``'s shape) a person marked the point invisible and the label is
    removed; elsewhere a NaN of flylib's keeps the project's value."""
    import pandas as pd

    levels = existing.columns.nlevels
    scorers = list(dict.fromkeys(existing.columns.get_level_values(0)))
    if levels not in (3, 4) or len(scorers) != 1:
        raise OutputError("the file's columns are not DeepLabCut's (scorer, bodyparts, coords)")
    parts = new.columns.get_level_values(1)
    coords = new.columns.get_level_values(2)
    if levels == 4:
        individuals = [
            i for i in dict.fromkeys(existing.columns.get_level_values(1)) if i != "single"
        ]
        if len(individuals) != 1:
            raise OutputError(
                f"a multi-animal project with individuals {', '.join(map(str, individuals))}: "
                "flylib's labels are one fly's; export to a new folder and merge by hand"
            )
        columns = [(scorers[0], individuals[0], b, c) for b, c in zip(parts, coords)]
    else:
        columns = [(scorers[0], b, c) for b, c in zip(parts, coords)]
    rows = list(new.index)
    if existing.index.nlevels == 1:  # an older project: one "labeled-data/<video>/img.png"
        rows = ["/".join(r) for r in rows]
    merged = existing.copy()
    for column in columns:
        if column not in merged.columns:
            merged[column] = np.nan
    values = new.to_numpy(dtype=np.float64)
    added = updated = 0
    fresh = [r for r in rows if r not in merged.index]
    if fresh:
        merged = pd.concat([merged, pd.DataFrame(np.nan, index=fresh, columns=merged.columns)])
        merged.index.names = existing.index.names
    position = {c: i for i, c in enumerate(merged.columns)}
    where = [position[c] for c in columns]
    for r, row in enumerate(rows):
        i = merged.index.get_loc(row)
        old = merged.iloc[i, where].to_numpy(dtype=np.float64)
        value = np.where(np.isfinite(values[r]), values[r], np.where(cleared[r], np.nan, old))
        if row in fresh:
            added += 1
        elif not np.array_equal(old, value, equal_nan=True):
            updated += 1
        merged.iloc[i, where] = value
    return merged, MergeCount(added, updated, len(existing.index) - updated)


def _write_collected(table, out: Path, scorer: str, cleared, report) -> list[Path]:
    """Write (or merge into) ``out``'s ``CollectedData_<scorer>`` files; the files written."""
    import pandas as pd

    csv_path, h5_path = out / f"CollectedData_{scorer}.csv", out / f"CollectedData_{scorer}.h5"
    existing = None
    source = h5_path if h5_path.is_file() else csv_path if csv_path.is_file() else None
    if source is not None:  # DeepLabCut trains from the .h5: it is the project's truth
        try:
            existing = (
                pd.read_hdf(source, DLC_H5_KEY) if source == h5_path else read_collected_csv(source)
            )
            table, count = merge_collected(existing, table, cleared)
        except (OSError, ValueError, KeyError, TypeError, ImportError, OutputError) as exc:
            raise OutputError(
                f"{source}: cannot merge flylib's labels into this file "
                f"({' '.join(str(exc).split())}); nothing was changed; move it away or export "
                "to another folder"
            ) from None
        if not count.changed and csv_path.is_file() and h5_path.is_file():
            report(f"{source}: unchanged ({count.kept} frames kept)")
            return []
    else:
        count = MergeCount(len(table.index), 0, 0)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
    backups = []
    for path in (csv_path, h5_path):
        if path.is_file():
            backup = path.with_name(f"{path.name}.{stamp}.bak")
            shutil.copy2(path, backup)
            backups.append(backup.name)
    with atomic_path(csv_path) as tmp:
        table.to_csv(tmp)
    with atomic_path(h5_path) as tmp:
        table.to_hdf(tmp, key=DLC_H5_KEY, mode="w")
    report(
        f"{csv_path}: {count.added} frames added, {count.updated} updated, {count.kept} kept"
        + (f" (backup: {', '.join(backups)})" if backups else "")
    )
    return [csv_path, h5_path]


def export_training_data(
    results: str | Path,
    directory: str | Path,
    *,
    footage_of: Callable[[Path], Mapping[str, Sequence[Path]]] | None = None,
    recording: str | Path | None = None,
    scorer: str = "flylib",
    protected: Mapping[str, str] | None = None,
    report: Callable[[str], None] = log.info,
) -> list[Path]:
    """Write the corrected frames of a ``results.h5`` (computed with a corrections sidecar) as
    DeepLabCut labeled data in ``directory``; returns the files written.

    ``footage_of``: recording directory -> ``{view: footage files}``, asked only once corrected
    frames are found; ``protected`` ``file -> role``: inputs no written file may land on;
    ``report`` gets one line per ``CollectedData`` file. :class:`ResultsError` without a corrected
    frame, :class:`FootageError` when footage is missing or unreadable."""
    import cv2

    from ..io import open_reader
    from ..results import PoseResult, open_checked

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
    recording = Path(recording) if recording else Path(result.meta.get("recording") or "")
    views = list(result.cameras.names)
    footage = footage_of(recording) if footage_of is not None and recording.is_dir() else {}
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
    # a point a person marked invisible: its label is removed from the project too
    invisible = touched[:, frames] & ~np.isfinite(result.pts2d[:, frames]).all(-1)
    points = [str(p) for p in result.skeleton.point_names]
    digits = max(4, len(str(result.n_frames - 1)))
    written: list[Path] = []
    for v, view in enumerate(views):
        files = footage[view]
        folder = files[0].stem if len(files) == 1 else view
        out = Path(directory) / "labeled-data" / folder
        images = [f"img{int(t):0{digits}d}.png" for t in frames]
        try:
            pixels = readers[view][[int(t) for t in frames]]
        except (FootageError, OSError, ValueError, IndexError) as exc:
            raise FootageError(f"{files[0]}: cannot read the corrected frames ({exc})") from None
        for name, rgb in zip(images, pixels):
            refuse_overwrite(out / name, dict(protected or {}), "the training images", force=True)
            if (out / name).exists():  # the project's own frame: kept
                continue
            with atomic_path(out / name) as tmp:
                ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
                if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
                    raise FootageError(f"{files[0]}: PNG encoding failed")
                tmp.write_bytes(data.tobytes())
            written.append(out / name)
        table = _dlc_frame(labels[v], folder, images, points, scorer)
        for name in (f"CollectedData_{scorer}.csv", f"CollectedData_{scorer}.h5"):
            refuse_overwrite(out / name, dict(protected or {}), "the training labels", force=True)
        cleared = np.repeat(invisible[v], 2, axis=-1)  # (F, P * 2): x and y of each point
        written += _write_collected(table, out, scorer, cleared, report)
    log.info(
        "training data: %d corrected frames x %d views in %s/labeled-data",
        len(frames),
        len(views),
        directory,
    )
    return written
