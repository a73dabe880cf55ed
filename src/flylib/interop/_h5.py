"""Opening another tool's HDF5 file with errors that name the file and the fix."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py

from ..errors import FlylibError, ImportFormatError, one_line
from ..hdf5_files import H5_READ_ERRORS, open_h5

__all__ = ["H5_READ_ERRORS", "open_foreign_h5", "reading_foreign_h5"]


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
    return open_h5(path, error=ImportFormatError, what=what, fix=hint)


@contextmanager
def reading_foreign_h5(path: str | Path, what: str, hint: str) -> Iterator[h5py.File]:
    """:func:`open_foreign_h5` as a context whose h5py read errors become one line.

    Errors raised while reading inside the block (:data:`H5_READ_ERRORS`) are re-raised
    as :class:`ImportFormatError` naming ``path``; flylib's own errors pass unchanged.
    """
    with open_foreign_h5(path, what, hint) as fh:
        try:
            yield fh
        except FlylibError:
            raise
        except H5_READ_ERRORS as exc:
            raise ImportFormatError(
                f"{path}: damaged or not a {what} ({type(exc).__name__}: {one_line(exc)}); {hint}"
            ) from None
