"""Opening another tool's HDF5 file with errors that name the file and the fix."""

from __future__ import annotations

from pathlib import Path

import h5py

from ..errors import ImportFormatError


def open_foreign_h5(path: str | Path, what: str, hint: str) -> h5py.File:
    """Open ``path`` read-only, or raise :class:`ImportFormatError`.

    Parameters
    ----------
    path
        The file to open.
    what
        What the file should be, for the message (e.g. ``"DeepLabCut .h5"``).
    hint
        What to check when it is missing (e.g. ``"check pose2d.import.files"``).
    """
    path = Path(path)
    if not path.is_file():
        raise ImportFormatError(f"{path}: no such {what}; {hint}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise ImportFormatError(f"{path}: not an HDF5 file ({exc})") from exc
