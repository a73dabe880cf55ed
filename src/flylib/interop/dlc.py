"""DeepLabCut-layout 2D keypoints (CSV and HDF5), which Lightning Pose also writes.

One file per camera view. The columns are a header MultiIndex ``scorer / bodyparts / coords``
(multi-animal files add ``individuals`` between scorer and bodyparts) with ``coords`` in
``x, y, likelihood``; the first column is the row index: a frame number, or an image path for
labelled data (``labeled-data/<video>/img047.png``, whose last number is the frame; newer files
split it over three index columns). Each row is placed at its frame index, whatever the rows' order:
frames no row gives are missing, a frame given twice is an error. Missing detections are empty cells
(NaN)."""

from __future__ import annotations

import csv
import io
import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import h5py
import numpy as np
import pandas as pd

from ..errors import FlylibError, ImportFormatError, one_line
from ..paths import atomic_path
from ._h5 import (
    DEFAULT_READ_BUDGET,
    H5_READ_ERRORS,
    checked_dataset,
    foreign_member,
    reading_foreign_h5,
)
from .safe_pickle import PICKLE_PARSE_ERRORS

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float


@dataclass
class ViewKeypoints:
    """2D keypoints of one camera view as another tool wrote them: the file's keypoint (body part /
    node) ``names`` (K), ``xy`` ``(T, K, 2)`` pixels (NaN = missing), ``conf`` ``(T, K)`` likelihood
    / score (NaN where the file gives none for a missing point) and the ``source`` file (for
    messages)."""

    names: list[str]
    xy: Float[np.ndarray, "T K 2"]
    conf: Float[np.ndarray, "T K"]
    source: Path


# pandas 3 parses floats exactly by default (and deprecates the option); pandas 2's default parser
# may be off by an ulp, so ask it for round-trip parsing explicitly.
_EXACT_FLOATS = {} if int(pd.__version__.split(".")[0]) >= 3 else {"float_precision": "round_trip"}


_HEADER_LEVELS = ("scorer", "individuals", "bodyparts", "coords")

#: What reading a CSV's text can raise: undecodable bytes, a malformed row, an oversized field, no
#: rows at all.
_CSV_ERRORS = (
    UnicodeDecodeError,
    csv.Error,
    pd.errors.ParserError,
    pd.errors.EmptyDataError,
    ValueError,
    OverflowError,
)


#: Most columns a DeepLabCut CSV may have: 3 per body part and individual (33,333 body parts of one
#: animal, or 38 points of 877 individuals).
MAX_CSV_COLUMNS = 100_000
#: Longest header line read (characters): 100,000 cells of about 160 characters.
_MAX_HEADER_LINE = 16 << 20


def _read_header(path: Path) -> list[list[str]]:
    """The header rows: the leading rows whose first cell is a DeepLabCut level name. Each line is
    read with a length bound and its columns counted before it is split, so a file of millions of
    columns is one error in milliseconds, not gigabytes of cells."""
    rows = []
    with path.open(newline="", encoding="utf-8") as fh:
        while True:
            line = fh.readline(_MAX_HEADER_LINE + 1)
            columns = line.count(",") + 1
            if len(line) > _MAX_HEADER_LINE or columns > MAX_CSV_COLUMNS:
                raise ImportFormatError(
                    f"{path}: line {len(rows) + 1} has more than {MAX_CSV_COLUMNS} columns "
                    "(a DeepLabCut CSV has 3 per body part and individual); check that this "
                    "is the tool's 2D output"
                )
            row = next(csv.reader([line]), [])
            if not row or row[0].strip() not in _HEADER_LEVELS:
                break
            rows.append(row)
    return rows


def _read_csv_frame(path: Path) -> pd.DataFrame:
    """The CSV as a DataFrame with the header rows as a column MultiIndex. The header is parsed
    here, not by pandas: with a multi-row ``header``, pandas takes a first data row whose cells are
    all empty (a frame with no detections) for the index-name row and drops that frame."""
    try:
        header = _read_header(path)
    except _CSV_ERRORS as exc:
        raise ImportFormatError(f"{path}: not a readable CSV ({one_line(exc)})") from None
    names = [row[0].strip() for row in header]
    if len(header) < 3 or not {"scorer", "bodyparts", "coords"} <= set(names):
        raise ImportFormatError(
            f"{path}: not a DeepLabCut CSV (expected header rows scorer/bodyparts/coords)"
        )
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ImportFormatError(f"{path}: header rows {repeated} given twice; keep one of each")
    # DeepLabCut's labelled-data files index rows by several columns (left blank in the header).
    first = header[0]
    n_index = 1 + next((i for i, cell in enumerate(first[1:]) if cell.strip()), len(first) - 1)
    widths = {len(row) for row in header}
    if len(widths) != 1 or n_index >= len(first):
        raise ImportFormatError(
            f"{path}: the header rows have different lengths or no keypoint columns"
        )
    columns = pd.MultiIndex.from_arrays([row[n_index:] for row in header], names=names)
    try:
        frame = pd.read_csv(
            path,
            header=None,
            skiprows=len(header),
            index_col=list(range(n_index)),
            names=list(range(len(first))),
            **_EXACT_FLOATS,
        )
    except pd.errors.EmptyDataError:  # a header and no frames
        frame = pd.DataFrame(np.empty((0, len(columns))))
    except _CSV_ERRORS as exc:
        raise ImportFormatError(f"{path}: malformed CSV row ({one_line(exc)})") from None
    if frame.shape[1] != len(columns):
        raise ImportFormatError(
            f"{path}: rows have {frame.shape[1]} value columns but the header names {len(columns)}"
        )
    frame.columns = columns
    return frame


def _floats(values: np.ndarray, path: Path) -> np.ndarray:
    """The frame's cells as float64; text cells (a column pandas could not parse) via float()."""
    if values.dtype != object:
        return values.astype(np.float64)
    values = values.copy()
    values[pd.isna(values)] = np.nan
    try:
        return values.astype(np.float64)
    except ValueError as exc:
        raise ImportFormatError(
            f"{path}: a keypoint column has a non-numeric cell ({exc})"
        ) from exc


#: Highest frame index a row may name (28 hours at 100 frames/s): rows are placed at their frame, so
#: an index is also an allocation.
MAX_FRAME_INDEX = 10_000_000
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def _frame_number(value, path: Path, row: int) -> int:
    """A row index's frame: an integer, or the last number in an image's name (``img047.png``)."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        number = int(value)
    elif isinstance(value, (float, np.floating)):
        if not (np.isfinite(value) and value == int(value)):
            raise ImportFormatError(
                f"{path}: data row {row + 1} has index {value!r}, which is no frame number; "
                "the first column must be the frame number (or the labelled image's path)"
            )
        number = int(value)
    else:
        text = str(value).strip()
        found = _LAST_NUMBER.search(Path(text.replace("\\", "/")).stem) if text else None
        if found is None:
            raise ImportFormatError(
                f"{path}: data row {row + 1} has index {value!r}, which names no frame; the first "
                "column must be the frame number (or the labelled image's path)"
            )
        number = int(found.group(1))
    if not 0 <= number <= MAX_FRAME_INDEX:
        raise ImportFormatError(
            f"{path}: data row {row + 1} names frame {number}, outside 0..{MAX_FRAME_INDEX}; "
            "the first column must be the frame number (or the labelled image's path)"
        )
    return number


def frame_rows(index: pd.Index, path: Path) -> np.ndarray:
    """The frame of each row of a DeepLabCut-layout table, from its row index; an index that names
    no frame, or a frame two rows give (both named), is an ImportFormatError."""
    values = (index.get_level_values(-1) if isinstance(index, pd.MultiIndex) else index).tolist()
    frames = np.array([_frame_number(v, path, i) for i, v in enumerate(values)], dtype=np.int64)
    order = np.argsort(frames, kind="stable")
    repeated = np.flatnonzero(np.diff(frames[order]) == 0)
    if repeated.size:
        first, second = sorted(order[repeated[0] : repeated[0] + 2])
        raise ImportFormatError(
            f"{path}: frame {frames[first]} is given twice (data rows {first + 1} and {second + 1}, "
            f"index {values[first]!r} and {values[second]!r}); keep one row per frame"
        )
    return frames


def _frame_to_view(frame: pd.DataFrame, path: Path, individual: str | None) -> ViewKeypoints:
    rows = frame_rows(frame.index, path)
    columns = frame.columns
    names = list(columns.names)
    if not {"scorer", "bodyparts", "coords"} <= set(names) or len(set(names)) != len(names):
        raise ImportFormatError(
            f"{path}: header has levels {names}; expected DeepLabCut's scorer/bodyparts/coords"
        )
    if "individuals" in names:
        found = list(dict.fromkeys(columns.get_level_values("individuals")))
        if individual is None and len(found) > 1:
            raise ImportFormatError(
                f"{path}: holds individuals {found}; set pose2d.import.individual to pick one"
            )
        chosen = individual if individual is not None else found[0]
        if chosen not in found:
            raise ImportFormatError(f"{path}: no individual {chosen!r} (has {found})")
        frame = frame.xs(chosen, axis=1, level="individuals")
        columns = frame.columns
    scorers = list(dict.fromkeys(columns.get_level_values("scorer")))
    if len(scorers) > 1:
        raise ImportFormatError(f"{path}: several scorers {scorers}; keep one per file")
    parts = [str(b) for b in columns.get_level_values("bodyparts")]
    coords = [str(c) for c in columns.get_level_values("coords")]
    column_of = {(b, c): i for i, (b, c) in enumerate(zip(parts, coords))}
    bodyparts = list(dict.fromkeys(parts))
    n_frames = int(rows.max()) + 1 if rows.size else 0
    if n_frames * frame.shape[1] * 8 > DEFAULT_READ_BUDGET:
        raise ImportFormatError(
            f"{path}: frame index {n_frames - 1} with {frame.shape[1]} value columns would take "
            f"{n_frames * frame.shape[1] * 8 / 2**30:.1f} GiB; check the file's first column"
        )
    values = np.full((n_frames, frame.shape[1]), np.nan)
    values[rows] = _floats(frame.to_numpy(), path)
    xy = np.full((n_frames, len(bodyparts), 2), np.nan)
    conf = np.full((n_frames, len(bodyparts)), np.nan)
    for k, part in enumerate(bodyparts):
        for c, coord in enumerate(("x", "y")):
            if (part, coord) not in column_of:
                raise ImportFormatError(f"{path}: body part {part!r} has no {coord!r} column")
            xy[:, k, c] = values[:, column_of[(part, coord)]]
        if (part, "likelihood") in column_of:
            conf[:, k] = values[:, column_of[(part, "likelihood")]]
        else:
            conf[:, k] = np.where(np.isfinite(xy[:, k]).all(-1), 1.0, np.nan)
    return ViewKeypoints(names=bodyparts, xy=xy, conf=conf, source=path)


def read_dlc_csv(path: Path, individual: str | None = None) -> ViewKeypoints:
    """Read a DeepLabCut / Lightning Pose per-view CSV; ``individual`` picks one of a multi-animal
    file's (required when several). A missing file or a header not in the DeepLabCut layout is an
    :class:`ImportFormatError`."""
    path = Path(path)
    if not path.is_file():
        raise ImportFormatError(f"{path}: no such DeepLabCut CSV; check pose2d.import.files")
    return _frame_to_view(_read_csv_frame(path), path, individual)


class _PlainUnpickler(pickle.Unpickler):
    """Unpickles only containers, strings and numbers: pandas' HDF5 metadata, nothing else."""

    def find_class(self, module, name):  # noqa: D102 - refuse every global
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def _plain_pickle(value) -> object:
    raw = value.tobytes() if isinstance(value, np.ndarray) else bytes(value)
    try:
        return _PlainUnpickler(io.BytesIO(raw)).load()
    except pickle.UnpicklingError:
        raise
    except PICKLE_PARSE_ERRORS as exc:
        raise pickle.UnpicklingError(f"{type(exc).__name__}: {exc}") from None


def as_text(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel()]


@dataclass
class _ForeignH5:
    """One open DeepLabCut ``.h5`` and how its members may be reached and read."""

    fh: h5py.File
    path: Path
    max_bytes: int
    what: str = "DeepLabCut .h5"
    hint: str = "check pose2d.import.files"

    def member(self, name: str):
        return foreign_member(self.fh, name, self.path, self.what, self.hint)

    def dataset(self, name: str) -> h5py.Dataset:
        found = checked_dataset(
            self.fh, name, self.path, self.what, self.hint, max_bytes=self.max_bytes
        )
        if found is None:
            raise KeyError(f"no dataset {name!r}")
        return found

    def read(self, name: str) -> np.ndarray:
        return self.dataset(name)[()]


def _pandas_group(source: _ForeignH5) -> str:
    """The path of the group pandas wrote the DataFrame to (DeepLabCut: ``df_with_missing``)."""
    if isinstance(source.member("df_with_missing"), h5py.Group):
        return "df_with_missing"
    for key in source.fh:
        found = source.member(key)
        if isinstance(found, h5py.Group) and "pandas_type" in found.attrs:
            return key
    raise ImportFormatError(f"{source.path}: holds no pandas DataFrame; not a DeepLabCut .h5")


def _real_block(values) -> np.ndarray:
    """A pandas value block as float64; other kinds (text, complex) are not keypoints."""
    values = np.asarray(values)
    if values.dtype.kind not in "biuf":
        raise ValueError(f"a value block of dtype {values.dtype}, not real numbers")
    return values.astype(np.float64)


def _fixed_frame(source: _ForeignH5, key: str) -> pd.DataFrame:
    """pandas ``format="fixed"``: level arrays + codes for the columns, one value block."""
    group = source.member(key)
    nlevels = int(group.attrs.get("block0_items_nlevels", 1))
    if int(group.attrs.get("nblocks", 1)) != 1 or nlevels < 3:
        raise ValueError("expected one float block with scorer/bodyparts/coords columns")
    levels, codes, names = [], [], []
    for i in range(nlevels):
        level = source.dataset(f"{key}/block0_items_level{i}")
        levels.append(as_text(level[()]))
        codes.append(np.asarray(source.read(f"{key}/block0_items_label{i}"), dtype=int))
        names.append(as_text([level.attrs["name"]])[0])
    columns = pd.MultiIndex(levels=levels, codes=codes, names=names)
    values = _real_block(source.read(f"{key}/block0_values"))
    return pd.DataFrame(values, columns=columns, index=_fixed_index(source, key, len(values)))


def _fixed_index(source: _ForeignH5, key: str, n_rows: int) -> pd.Index:
    """A pandas ``format="fixed"`` frame's row index (a MultiIndex's last level: the image)."""
    group = source.member(key)
    if "axis1_nlevels" in group.attrs:
        last = int(group.attrs["axis1_nlevels"]) - 1
        level = source.read(f"{key}/axis1_level{last}")
        codes = np.asarray(source.read(f"{key}/axis1_label{last}"), dtype=int)
        values = np.asarray(level)[codes]
    else:
        values = np.asarray(source.read(f"{key}/axis1"))
    if len(values) != n_rows:
        raise ValueError(f"{len(values)} row labels for {n_rows} rows")
    return pd.Index(as_text(values) if values.dtype.kind in "SOU" else values)


def _table_frame(source: _ForeignH5, key: str) -> pd.DataFrame:
    """pandas ``format="table"`` (what DeepLabCut writes): a PyTables table of value blocks."""
    group = source.member(key)
    table = source.dataset(f"{key}/table")
    info = _plain_pickle(group.attrs["info"])
    names = list((info.get(1) or {}).get("names") or [])
    data = table[()]
    blocks, columns = [], []
    for field in data.dtype.names:
        if not field.startswith("values_block_"):
            continue
        values = _real_block(data[field]).reshape(len(data), -1)
        blocks.append(values)
        columns += [tuple(c) for c in _plain_pickle(table.attrs[f"{field}_kind"])]
    index = pd.MultiIndex.from_tuples(columns, names=names or None)
    rows = data["index"] if "index" in data.dtype.names else np.arange(len(data))
    rows = pd.Index(as_text(rows) if rows.dtype.kind in "SOU" else rows)
    return pd.DataFrame(np.concatenate(blocks, axis=1), columns=index, index=rows)


def read_dlc_h5(
    path: Path, individual: str | None = None, *, max_bytes: int = DEFAULT_READ_BUDGET
) -> ViewKeypoints:
    """Read a DeepLabCut per-view HDF5 (a pandas DataFrame, key ``df_with_missing``).

    Read with h5py (no PyTables needed), for both pandas layouts: ``format="table"`` (DeepLabCut's)
    and ``format="fixed"``. pandas keeps the column names as protocol-0 pickles of plain
    lists/tuples, loaded with an unpickler that refuses every class. Read as
    :mod:`flylib.interop._h5` reads a foreign file (``max_bytes`` per dataset). A missing file, or
    one holding no DeepLabCut-layout DataFrame, is an :class:`ImportFormatError`."""
    path = Path(path)
    hint = "or import the CSV beside it (format: dlc_csv)"
    with reading_foreign_h5(path, "DeepLabCut .h5", "check pose2d.import.files") as fh:
        source = _ForeignH5(fh, path, max_bytes)
        key = _pandas_group(source)
        kind = as_text([source.member(key).attrs.get("pandas_type", b"")])[0]
        try:
            if kind == "frame_table":
                frame = _table_frame(source, key)
            elif kind == "frame":
                frame = _fixed_frame(source, key)
            else:
                raise ValueError(f"pandas_type {kind!r} is not a DataFrame")
        except FlylibError:
            raise
        except pickle.UnpicklingError as exc:
            raise ImportFormatError(
                f"{path}: refused or unreadable pickled pandas metadata ({one_line(exc)}); {hint}"
            ) from None
        except (*H5_READ_ERRORS, AttributeError, IndexError, EOFError) as exc:
            raise ImportFormatError(
                f"{path}: not a DeepLabCut DataFrame ({one_line(exc)}); {hint}"
            ) from None
    return _frame_to_view(frame, path, individual)


def dlc_frame(
    xy: Float[np.ndarray, "T K 2"],
    likelihood: Float[np.ndarray, "T K"] | None,
    bodyparts: list[str],
    scorer: str = "flylib",
) -> pd.DataFrame:
    """A DeepLabCut-layout DataFrame of one view's ``(T, K, 2)`` points; ``likelihood`` ``(T, K)``
    defaults to 1 where a point is present and is NaN (an empty cell) wherever ``x``/``y`` are."""
    xy = np.asarray(xy, dtype=np.float64)
    n_frames, n_parts, _ = xy.shape
    if len(bodyparts) != n_parts:
        raise ValueError(f"{len(bodyparts)} body part names for {n_parts} points")
    # a missing point has no likelihood: no row reads as "somewhere, with confidence c"
    given = 1.0 if likelihood is None else np.asarray(likelihood, np.float64)
    likelihood = np.where(np.isfinite(xy).all(-1), given, np.nan)
    values = np.concatenate([xy, likelihood[..., None]], axis=-1).reshape(n_frames, n_parts * 3)
    columns = pd.MultiIndex.from_product(
        [[scorer], list(bodyparts), ["x", "y", "likelihood"]],
        names=["scorer", "bodyparts", "coords"],
    )
    return pd.DataFrame(values, columns=columns, index=pd.RangeIndex(n_frames))


def write_dlc_csv(
    path: Path,
    xy: Float[np.ndarray, "T K 2"],
    likelihood: Float[np.ndarray, "T K"] | None,
    bodyparts: list[str],
    scorer: str = "flylib",
) -> Path:
    """Write one view's points (``xy`` ``(T, K, 2)`` pixels, NaN = missing, written as empty cells;
    ``likelihood`` ``(T, K)`` or ``None`` for 1 where present) as a DeepLabCut CSV (readable by DLC,
    Lightning Pose, Anipose), atomically; returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        dlc_frame(xy, likelihood, bodyparts, scorer).to_csv(tmp)
    return path
