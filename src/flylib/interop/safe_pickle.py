"""Loading another tool's pickle without letting it run code.

A pickle names the callables that rebuild its objects (``module.name`` globals) and the unpickler
calls them, so a plain :func:`pickle.load` of a downloaded file can run anything. DeepFly3D's files
(the 2D result and the calibration) only hold dicts, lists, numbers, strings and NumPy arrays, so
:func:`load_restricted` admits exactly the globals those need -- NumPy's array/dtype/scalar
reconstruction helpers under both their NumPy 1.x (``numpy.core``) and 2.x (``numpy._core``) module
paths, and the builtin containers and scalars -- and refuses every other global before it is
imported, let alone called.

Nor may a small file make the loader allocate without bound (a "bomb"): the file's size, its number
of pickle opcodes (each object it builds costs at least one) and every declared length are checked
before anything is built; the admitted callables that allocate (NumPy's array constructors,
``bytes(n)``, ``bytearray(n)``, ``str``) are wrapped to bound what they allocate; and the loaded
value is measured as the tree its consumers will walk -- a list holding the same list 16 times,
seven levels deep, is 290 bytes on disk and 500 million numbers to :func:`numpy.asarray` -- so
shared, deep or cyclic structures are one clear error in milliseconds."""

from __future__ import annotations

import io
import math
import pickle
import pickletools
from pathlib import Path

import numpy as np

from ..config.loading import shape_problem
from ..errors import ImportFormatError

#: Largest pickle file read (a 100,000-frame DeepFly3D 2D result is about 0.5 GB).
MAX_PICKLE_BYTES = 2 << 30
#: Most pickle opcodes in one file: DeepFly3D's files hold a few hundred (their arrays are single
#: binary blobs); each built object costs at least one opcode.
MAX_PICKLE_OPCODES = 2_000_000
#: Most values the loaded structure may expand to when walked as a tree (containers, array elements
#: and scalars; 2**28, 2 GiB as float64).
MAX_EXPANDED_VALUES = 1 << 28
#: Deepest nesting of containers (DeepFly3D's data nests 3 deep).
MAX_NESTING = 32
#: Most bytes one call of an admitted constructor may allocate. A pickle's arrays carry their data
#: in the file (``_reconstruct`` of an empty array, then its bytes); only a crafted file asks a
#: constructor for size.
MAX_ALLOCATION_BYTES = 256 << 20


class PickleBomb(pickle.UnpicklingError):
    """A pickle would allocate or expand beyond the bounds above."""


def _bounded_nbytes(shape, dtype) -> None:
    """Refuse an array allocation of ``shape`` x ``dtype`` beyond :data:`MAX_ALLOCATION_BYTES`."""
    dims = (shape,) if isinstance(shape, int) else tuple(shape)
    if not all(isinstance(n, int | np.integer) for n in dims):
        raise pickle.UnpicklingError(f"array shape {shape!r} is not a tuple of integers")
    itemsize = max(np.dtype(dtype).itemsize, 1)
    nbytes = math.prod(max(int(n), 0) for n in dims) * itemsize
    if nbytes > MAX_ALLOCATION_BYTES:
        raise PickleBomb(
            f"an array of shape {tuple(int(n) for n in dims)} and dtype {np.dtype(dtype)} "
            f"({nbytes} bytes, more than {MAX_ALLOCATION_BYTES})"
        )


class _PickledNdarray(np.ndarray):
    """A pickle's ``numpy.ndarray``: the type for ``_reconstruct``; called, a bounded allocation."""

    def __new__(cls, shape, dtype=float, *args, **kwargs):
        _bounded_nbytes(shape, dtype)
        return np.ndarray.__new__(np.ndarray, shape, dtype, *args, **kwargs)


def _guard_reconstruct(reconstruct):
    def _reconstruct(subtype, shape, dtype):
        if subtype is not _PickledNdarray:
            raise pickle.UnpicklingError(f"_reconstruct of {subtype!r}, not numpy.ndarray")
        _bounded_nbytes(shape, np.uint8)
        return reconstruct(np.ndarray, shape, dtype)

    return _reconstruct


def _guard_scalar(scalar):
    def _scalar(dtype, *args):
        if not isinstance(dtype, np.dtype):
            raise pickle.UnpicklingError(f"numpy scalar of {type(dtype).__name__}, not a dtype")
        _bounded_nbytes((), dtype)
        return scalar(dtype, *args)

    return _scalar


def _guard_sized(kind: type):
    """``bytes`` / ``bytearray`` as a pickle may call them: ``kind(n)`` allocates n bytes."""

    def _make(*args):
        if args and isinstance(args[0], int) and not isinstance(args[0], bool):
            _bounded_nbytes((args[0],), np.uint8)
        return kind(*args)

    return _make


def _plain_str(*args):
    """``str`` of text or a number only: ``str(nested list)`` would print it whole."""
    if args and not isinstance(args[0], str | bytes | int | float | complex | bool):
        raise pickle.UnpicklingError(f"str() of a {type(args[0]).__name__}")
    return str(*args)


def _numpy_helpers() -> dict[tuple[str, str], object]:
    # Resolved from the running NumPy's private module (1.x: numpy.core, 2.x: numpy._core) so a file
    # written under either version loads without importing the deprecated alias.
    try:
        from numpy._core import multiarray, numeric
    except ImportError:  # NumPy 1.x before 1.25 has no numpy._core
        from numpy.core import multiarray, numeric  # type: ignore[no-redef]
    helpers = {
        "multiarray": {
            "_reconstruct": _guard_reconstruct(multiarray._reconstruct),
            "scalar": _guard_scalar(multiarray.scalar),
        },
        "numeric": {"_frombuffer": numeric._frombuffer},  # a view of bytes already read
    }
    out: dict[tuple[str, str], object] = {
        ("numpy", "ndarray"): _PickledNdarray,
        ("numpy", "dtype"): np.dtype,
    }
    for package in ("numpy.core", "numpy._core"):
        for module, names in helpers.items():
            for name, obj in names.items():
                out[(f"{package}.{module}", name)] = obj
    return out


def _latin1_bytes(text, encoding: str = "latin1") -> bytes:
    """``_codecs.encode`` as pickles of bytes use it: latin-1 text to bytes, no other codec."""
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

    plain = ("dict", "list", "tuple", "set", "frozenset", "int", "float", "complex", "bool")
    out: dict[tuple[str, str], object] = {}
    for module in ("builtins", "__builtin__"):  # __builtin__: pickles written by Python 2
        out.update({(module, name): getattr(builtins, name) for name in plain})
        out[(module, "bytes")] = _guard_sized(bytes)
        out[(module, "bytearray")] = _guard_sized(bytearray)
        out[(module, "str")] = _plain_str
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


#: What :mod:`pickle` raises on bytes that are not a well-formed pickle: its own UnpicklingError,
#: the ones its documentation lists (AttributeError, EOFError, ImportError, IndexError), and what
#: the opcodes' arguments and the admitted NumPy constructors raise on bad values (struct sizes,
#: memo keys, dtype strings, text encodings, absurd lengths, nesting deeper than the interpreter's
#: stack).
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


def _prescan(data: bytes) -> None:
    """Refuse, before anything is built, a declared length beyond the file or too many opcodes."""
    for count, _ in enumerate(pickletools.genops(io.BytesIO(data)), 1):
        if count > MAX_PICKLE_OPCODES:
            raise PickleBomb(f"more than {MAX_PICKLE_OPCODES} pickle opcodes")


def _members(obj) -> list:
    if isinstance(obj, dict):
        return [*obj.keys(), *obj.values()]
    if isinstance(obj, list | tuple | set | frozenset):
        return list(obj)
    if isinstance(obj, np.ndarray) and obj.dtype.hasobject:
        return list(obj.ravel())
    return []


def _values(obj) -> int:
    """A numeric array counts its elements; anything else counts 1 (plus its members)."""
    return int(obj.size) if isinstance(obj, np.ndarray) and not obj.dtype.hasobject else 1


def _measure(value) -> None:
    """Refuse a loaded value that, walked as a tree, expands beyond :data:`MAX_EXPANDED_VALUES`
    values, nests deeper than :data:`MAX_NESTING` or contains itself
    (:func:`flylib.config.loading.shape_problem`)."""
    problem = shape_problem(
        value,
        children=_members,
        weight=_values,
        max_values=MAX_EXPANDED_VALUES,
        max_depth=MAX_NESTING,
    )
    if problem:
        raise PickleBomb(f"its value {problem}")


def load_restricted(path: str | Path, what: str):
    """Unpickle ``path`` admitting only plain data and NumPy arrays, within bounds (``what``: the
    file's kind, for messages); a global outside :data:`ALLOWED_GLOBALS` (never imported), a bomb
    or an unreadable pickle is an :class:`ImportFormatError` naming the file."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_PICKLE_BYTES:
            raise PickleBomb(f"the file is {size} bytes, more than {MAX_PICKLE_BYTES}")
        data = path.read_bytes()
        _prescan(data)
        value = _RestrictedUnpickler(io.BytesIO(data)).load()
        _measure(value)
        return value
    except RefusedGlobal as exc:
        raise ImportFormatError(
            f"{path}: refused to load {what} pickle: it names the global {exc.qualname!r}, "
            "and a DeepFly3D file holds only dicts, lists, numbers and NumPy arrays "
            "(loading it could run code); re-save the data from a trusted source"
        ) from None
    except PickleBomb as exc:
        raise ImportFormatError(
            f"{path}: refused to load {what} pickle: {exc}, far beyond what a DeepFly3D "
            "file holds (a crafted or damaged file); re-save the data from a trusted source"
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
