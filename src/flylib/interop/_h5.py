"""Opening another tool's HDF5 file with errors that name the file and the fix."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py

from ..errors import FlylibError, ImportFormatError

#: What h5py raises while reading a damaged or unexpected file: OSError for storage-level
#: damage (a bad B-tree, a failed filter or checksum, a truncated file), KeyError for a
#: link that does not resolve, ValueError/TypeError for a dtype or selection that does
#: not convert, RuntimeError for a few low-level HDF5 failures.
H5_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError)


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
    except H5_READ_ERRORS as exc:
        raise ImportFormatError(f"{path}: not an HDF5 file ({_one_line(exc)})") from exc


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
                f"{path}: damaged or not a {what} ({type(exc).__name__}: {_one_line(exc)}); {hint}"
            ) from None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]
