"""Loading another tool's pickle without letting it run code.

A pickle names the callables that rebuild its objects (``module.name`` globals) and
the unpickler calls them, so a plain :func:`pickle.load` of a downloaded file can run
anything. DeepFly3D's files (the 2D result and the calibration) only hold dicts,
lists, numbers, strings and NumPy arrays, so :func:`load_restricted` admits exactly
the globals those need -- NumPy's array/dtype/scalar reconstruction helpers under
both their NumPy 1.x (``numpy.core``) and 2.x (``numpy._core``) module paths, and
the builtin containers and scalars -- and refuses every other global before it is
imported, let alone called.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from ..errors import ImportFormatError


def _numpy_helpers() -> dict[tuple[str, str], object]:
    # Resolved from the running NumPy's private module (1.x: numpy.core, 2.x: numpy._core)
    # so a file written under either version loads without importing the deprecated alias.
    try:
        from numpy._core import multiarray, numeric
    except ImportError:  # NumPy 1.x before 1.25 has no numpy._core
        from numpy.core import multiarray, numeric  # type: ignore[no-redef]
    helpers = {
        "multiarray": {"_reconstruct": multiarray._reconstruct, "scalar": multiarray.scalar},
        "numeric": {"_frombuffer": numeric._frombuffer},
    }
    out: dict[tuple[str, str], object] = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
    }
    for package in ("numpy.core", "numpy._core"):
        for module, names in helpers.items():
            for name, obj in names.items():
                out[(f"{package}.{module}", name)] = obj
    return out


def _latin1_bytes(text, encoding: str = "latin1") -> bytes:
    """``_codecs.encode`` as pickles of bytes use it: latin-1 text to bytes, nothing else
    (no other codec -- compressors, ROT13, unknown names -- is reachable from a file)."""
    if (
        not isinstance(text, str)
        or not isinstance(encoding, str)
        or encoding.lower().replace("-", "").replace("_", "") not in ("latin1", "iso88591")
    ):
        raise pickle.UnpicklingError(f"_codecs.encode with {type(text).__name__} and {encoding!r}")
    return text.encode("latin-1")


def _builtins() -> dict[tuple[str, str], object]:
    import builtins
    from collections import OrderedDict

    plain = (
        "dict",
        "list",
        "tuple",
        "set",
        "frozenset",
        "int",
        "float",
        "complex",
        "bool",
        "str",
        "bytes",
        "bytearray",
    )
    out: dict[tuple[str, str], object] = {}
    for module in ("builtins", "__builtin__"):  # __builtin__: pickles written by Python 2
        out.update({(module, name): getattr(builtins, name) for name in plain})
    # Python 3 writes bytes in protocols 0-2 as _codecs.encode(text, "latin1").
    out[("_codecs", "encode")] = _latin1_bytes
    out[("collections", "OrderedDict")] = OrderedDict
    return out


#: ``(module, name) -> object`` of every global a restricted load may use.
ALLOWED_GLOBALS: dict[tuple[str, str], object] = {**_numpy_helpers(), **_builtins()}


class RefusedGlobal(pickle.UnpicklingError):
    """A pickle names a global outside :data:`ALLOWED_GLOBALS`."""

    def __init__(self, module: str, name: str):
        super().__init__(f"{module}.{name}")
        self.qualname = f"{module}.{name}"


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        try:
            return ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise RefusedGlobal(module, name) from None


#: What :mod:`pickle` raises on bytes that are not a well-formed pickle: its own
#: UnpicklingError, the ones its documentation lists (AttributeError, EOFError,
#: ImportError, IndexError), and what the opcodes' arguments and the admitted NumPy
#: constructors raise on bad values (struct sizes, memo keys, dtype strings, text
#: encodings, absurd lengths, nesting deeper than the interpreter's stack).
PICKLE_PARSE_ERRORS = (
    pickle.UnpicklingError,
    AttributeError,
    EOFError,
    ImportError,
    IndexError,
    KeyError,
    ValueError,
    TypeError,
    OverflowError,
    MemoryError,
    RecursionError,
)


def load_restricted(path: str | Path, what: str):
    """Unpickle ``path`` admitting only plain data and NumPy arrays.

    Parameters
    ----------
    path
        The pickle file.
    what
        What the file should be, for messages (e.g. ``"DeepFly3D 2D result"``).

    Returns
    -------
    object
        The unpickled value (dicts, lists, tuples, numbers, strings, NumPy arrays).

    Raises
    ------
    ImportFormatError
        The file names a global outside :data:`ALLOWED_GLOBALS` (the message names
        the file and the refused global; nothing of it was imported or called), or
        it is not a readable pickle.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return _RestrictedUnpickler(fh).load()
    except RefusedGlobal as exc:
        raise ImportFormatError(
            f"{path}: refused to load {what} pickle: it names the global {exc.qualname!r}, "
            "and a DeepFly3D file holds only dicts, lists, numbers and NumPy arrays "
            "(loading it could run code); re-save the data from a trusted source"
        ) from None
    except OSError as exc:
        raise ImportFormatError(
            f"{path}: cannot read the {what} pickle ({exc.strerror or exc})"
        ) from None
    except PICKLE_PARSE_ERRORS as exc:
        detail = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise ImportFormatError(
            f"{path}: not a readable {what} pickle ({type(exc).__name__}: {detail})"
        ) from None
