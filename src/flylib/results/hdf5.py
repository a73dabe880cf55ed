"""Opening and creating HDF5 files: :func:`open_hdf5`, the one read-only opener (flylib's files
and other tools', with one-line errors), :func:`open_checked` (the format-version check), the meta
JSON, and :func:`create_file` (HDF5 1.8's checksummed object headers)."""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path

import h5py

from ..errors import FlylibError, ResultsError, one_line
from ..paths import out_of_space
from .checksums import damaged
from .guard import guard_file

#: The results.h5 schema version this code writes and accepts.
FORMAT_VERSION = 2
# HDF5 1.8's file format: object headers, link tables and the superblock carry checksums
# (readable by any HDF5 >= 1.8, i.e. since 2008).
_LIBVER = ("v108", "latest")

#: What h5py raises while reading a damaged or unexpected file: OSError for storage-level damage
#: (a bad B-tree, a failed filter or checksum, a truncated file), KeyError for a link that does not
#: resolve, ValueError/TypeError for a dtype or selection that does not convert, RuntimeError for
#: a few low-level HDF5 failures.
H5_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError)


def create_file(path: str | Path) -> h5py.File:
    """A new HDF5 file in the checksummed metadata format."""
    return h5py.File(path, "w", libver=_LIBVER)


def open_hdf5(
    path: str | Path,
    fix: str,
    what: str = "HDF5 file",
    *,
    error: type[FlylibError] = ResultsError,
    guard: bool = True,
) -> h5py.File:
    """Open ``path`` read-only; a missing or unreadable file is one ``error`` naming it, ``what``
    it should be (e.g. ``"DeepLabCut .h5"``) and the ``fix`` (e.g. ``"re-run the workflow"``).

    ``error``: :class:`~flylib.errors.ResultsError` for flylib's files,
    :class:`~flylib.errors.ImportFormatError` for another tool's. ``guard``: check the whole file
    first (:func:`~flylib.results.guard.guard_file`); ``False`` only for another tool's file,
    whose readers check each member they read (:mod:`flylib.interop._h5`).
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such {what}; {fix}")
    try:
        f = h5py.File(path, "r")
    except H5_READ_ERRORS as err:
        raise error(f"{path}: not a readable {what} ({one_line(err)}); {fix}") from None
    if guard:
        try:
            guard_file(f, path, fix, error=error)
        except FlylibError:
            f.close()
            raise
        except H5_READ_ERRORS as err:  # a link table or object header HDF5 cannot load
            f.close()
            if error is ResultsError:
                raise damaged(path, "an HDF5 object", err) from None
            raise error(f"{path}: not a readable {what} ({one_line(err)}); {fix}") from None
    return f


@contextmanager
def open_checked(path: str | Path, rerun: str = "re-run the workflow") -> Iterator[h5py.File]:
    """Open a results or stage file read-only, checking its version: missing, not HDF5, not
    flylib's or another format version is a ResultsError that tells the user to ``rerun``."""
    path = Path(path)
    with open_hdf5(path, rerun) as f:
        try:
            version = read_meta_from(f).get("deeperfly_format_version")
        except (OSError, KeyError, RuntimeError) as err:
            raise damaged(path, "its root attributes", err) from None
        if version is None:
            raise ResultsError(
                f"{path}: not a flylib file (no format version in its meta); {rerun} to regenerate it"
            )
        if version != FORMAT_VERSION:
            raise ResultsError(
                f"{path}: format version {version!r}, expected {FORMAT_VERSION}; {rerun} to regenerate it"
            )
        try:
            yield f
        except (OSError, RuntimeError) as err:  # a damaged object header, link table, ...
            if out_of_space(err) is not None:
                raise  # a write in the block failed (atomic_path reports it), not this file
            raise damaged(path, "an HDF5 object", err) from None
        except KeyError as err:
            if "Unable to" not in str(err):  # h5py's words for an object HDF5 could not load
                raise
            raise damaged(path, "an HDF5 object", err) from None


#: What reading a damaged file raises below flylib: :data:`H5_READ_ERRORS`, and
#: IndexError/AttributeError (JSON attributes of an unexpected type).
_DAMAGE_ERRORS = (*H5_READ_ERRORS, IndexError, AttributeError)


@contextmanager
def read_checked(path: str | Path, rerun: str) -> Iterator[h5py.File]:
    """:func:`open_checked` for the loaders: a read that fails inside the block (the file is
    damaged) raises :class:`ResultsError` naming the file, not h5py's error."""
    try:
        with open_checked(path, rerun) as f:
            yield f
    except ResultsError:
        raise
    except FlylibError as err:  # stored content a constructor refuses (e.g. a skeleton's limbs)
        detail = " ".join(str(err).split())[:300]
        raise ResultsError(f"{path}: invalid content ({detail}); {rerun}") from None
    except _DAMAGE_ERRORS as err:
        detail = " ".join(str(err).split())[:300]
        raise ResultsError(
            f"{path}: damaged or unreadable ({type(err).__name__}: {detail}); {rerun}"
        ) from None


def read_meta_from(f: h5py.File) -> dict:
    """The ``meta`` JSON of an open file (empty when absent or unreadable)."""
    raw = f.attrs.get("meta")
    if raw is None:
        return {}
    try:
        meta = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
    except (json.JSONDecodeError, TypeError):
        return {}
    return meta if isinstance(meta, dict) else {}


def read_meta(path: str | Path) -> dict:
    """The ``meta`` JSON of a flylib HDF5 file (no version check; empty if it has none); a file
    that is not HDF5, or whose root object is damaged, is a ResultsError naming it."""
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise ResultsError(f"{path}: not a readable HDF5 file ({err})") from None
    with f:
        try:
            return read_meta_from(f)
        except (OSError, KeyError, RuntimeError) as err:  # a damaged root object header
            raise damaged(path, "its root attributes", err) from None


def new_meta(stage: str, extra: Mapping | None = None) -> dict:
    from .. import __version__

    return {
        **(extra or {}),
        "deeperfly_format_version": FORMAT_VERSION,
        "flylib_version": __version__,
        "created_utc": datetime.now(UTC).isoformat(),
        "stage": stage,
    }
