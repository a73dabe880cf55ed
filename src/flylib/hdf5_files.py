"""Opening an HDF5 file for reading, flylib's own or another tool's, with one-line errors
that name the file and the fix."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from .errors import FlylibError, one_line

if TYPE_CHECKING:  # pragma: no cover
    import h5py

#: What h5py raises while reading a damaged or unexpected file: OSError for storage-level
#: damage (a bad B-tree, a failed filter or checksum, a truncated file), KeyError for a
#: link that does not resolve, ValueError/TypeError for a dtype or selection that does
#: not convert, RuntimeError for a few low-level HDF5 failures.
H5_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError)


def open_h5(path: str | Path, *, error: type[FlylibError], what: str, fix: str) -> h5py.File:
    """Open ``path`` read-only; a missing or unreadable file is one ``error`` naming it.

    Parameters
    ----------
    path
        The file.
    error
        The error class to raise (:class:`~flylib.errors.ResultsError` for flylib's
        files, :class:`~flylib.errors.ImportFormatError` for another tool's).
    what
        What the file should be, for the message (e.g. ``"DeepLabCut .h5"``).
    fix
        What the user should do (e.g. ``"re-run the workflow"``).
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such {what}; {fix}")
    try:
        return h5py.File(path, "r")
    except H5_READ_ERRORS as err:
        raise error(f"{path}: not a readable {what} ({one_line(err)}); {fix}") from None
