"""SLEAP analysis HDF5 (``sleap-convert --format analysis``), one file per camera view.

Datasets used: ``node_names`` (K,), ``tracks`` and, when present, ``point_scores``. SLEAP writes its
matrices transposed for MATLAB by default, so ``tracks`` is stored as ``(n_tracks, 2, K, T)`` and
``point_scores`` as ``(n_tracks, K, T)``; files written without the transpose hold
``(T, K, 2, n_tracks)`` and ``(T, K, n_tracks)``. Both are accepted (told apart by where the
length-2 coordinate axis sits)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import ImportFormatError
from ._h5 import DEFAULT_READ_BUDGET, read_checked, reading_foreign_h5
from .calib_checks import numeric_array
from .dlc import ViewKeypoints, as_text as _decode

log = logging.getLogger(__name__)


def read_sleap_analysis(
    path: Path, track: int | str | None = None, *, max_bytes: int = DEFAULT_READ_BUDGET
) -> ViewKeypoints:
    """Read one track (index or name; required when the file holds several) of a SLEAP analysis
    HDF5: node names, ``(T, K, 2)`` pixels and ``(T, K)`` point scores (1 where the file has no
    scores and the point is present).

    Read as :mod:`flylib.interop._h5` reads a foreign file (``max_bytes`` per dataset: its
    :func:`~flylib.interop._h5.read_budget`). A missing file, no ``tracks``/``node_names``, or an
    ambiguous track is an :class:`ImportFormatError`."""
    path = Path(path)
    hint = "export it with sleap-convert --format analysis (or sleap_io.save_analysis_h5)"
    what = "SLEAP analysis file"
    with reading_foreign_h5(path, what, hint) as fh:

        def read(name: str):
            return read_checked(fh, name, path, what, hint, max_bytes=max_bytes)

        raw_names, raw_tracks = read("node_names"), read("tracks")
        if raw_tracks is None or raw_names is None:
            raise ImportFormatError(
                f"{path}: lacks 'tracks'/'node_names'; export it with sleap-convert --format analysis"
            )
        names = _decode(raw_names)
        tracks = numeric_array(raw_tracks, str(path), "tracks", hint)
        raw_scores = read("point_scores")
        scores = (
            None
            if raw_scores is None
            else numeric_array(raw_scores, str(path), "point_scores", hint)
        )
        raw_track_names = read("track_names")
        track_names = [] if raw_track_names is None else _decode(raw_track_names)
    n_nodes = len(names)
    if tracks.ndim != 4:
        raise ImportFormatError(
            f"{path}: 'tracks' has shape {tracks.shape}, expected 4 axes; {hint}"
        )
    if tracks.shape[1] == 2 and tracks.shape[2] == n_nodes:  # MATLAB-transposed layout
        tracks = tracks.T  # -> (T, K, 2, n_tracks)
        scores = None if scores is None else scores.T  # -> (T, K, n_tracks)
    elif not (tracks.shape[1] == n_nodes and tracks.shape[2] == 2):
        raise ImportFormatError(
            f"{path}: 'tracks' shape {tracks.shape} does not fit {n_nodes} nodes; {hint}"
        )
    if scores is not None and scores.shape != tracks.shape[:2] + tracks.shape[3:]:
        raise ImportFormatError(
            f"{path}: 'point_scores' shape does not fit 'tracks' {tracks.shape}; {hint}"
        )
    n_tracks = tracks.shape[-1]
    if n_tracks == 0:  # what SLEAP writes for a video in which nothing was detected
        log.warning(
            "%s: holds no tracks (SLEAP detected nothing in this view); its %d frames are "
            "imported as missing",
            path,
            tracks.shape[0],
        )
        xy = np.full(tracks.shape[:3], np.nan)
        return ViewKeypoints(names=names, xy=xy, conf=np.full(xy.shape[:2], np.nan), source=path)
    if track is None:
        if n_tracks > 1:
            raise ImportFormatError(
                f"{path}: holds {n_tracks} tracks {track_names or ''}; set pose2d.import.track"
            )
        index = 0
    elif isinstance(track, str) and not track.isdigit():
        if track not in track_names:
            raise ImportFormatError(f"{path}: no track named {track!r} (has {track_names})")
        index = track_names.index(track)
    else:
        index = int(track)
        if not 0 <= index < n_tracks:
            raise ImportFormatError(f"{path}: track {index} out of range (0..{n_tracks - 1})")
    xy = np.ascontiguousarray(tracks[..., index])
    present = np.isfinite(xy).all(-1)
    if scores is None:
        conf = np.where(present, 1.0, np.nan)
    else:
        conf = np.where(present, scores[..., index], np.nan)
    return ViewKeypoints(names=names, xy=xy, conf=conf, source=path)
