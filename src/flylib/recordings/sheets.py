"""Recordings sheets: a ``recordings`` value that is the path of a ``.tsv`` or ``.csv`` file, one
recording per row."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import ConfigError

#: A recordings sheet's suffix -> its column separator: a ``.tsv`` sheet, or the ``.csv`` a
#: spreadsheet program saves.
SHEET_SEPARATORS = {".tsv": "\t", ".csv": ","}


def is_sheet(text: str) -> bool:
    """Whether a listed ``recordings`` value names a sheet (a ``.tsv`` or ``.csv`` file)."""
    return Path(text).suffix.lower() in SHEET_SEPARATORS and not Path(text).is_dir()


def read_sheet(path: Path) -> list[dict]:
    """Entries of a ``.tsv`` (tab-separated) or ``.csv`` (comma-separated) sheet: columns ``path``
    and optional ``outdir``, ``import_format``, ``import_files`` (``view=file`` pairs separated by
    ``;``), ``session``; a relative ``path`` is relative to the sheet's folder."""
    import pandas as pd

    if not path.is_file():
        raise ConfigError(f"recordings: sheet {path} does not exist; create it or list directories")
    separator = SHEET_SEPARATORS[path.suffix.lower()]
    try:  # utf-8-sig: the byte-order mark spreadsheet programs put before the header
        sheet = pd.read_csv(
            path, sep=separator, dtype=str, comment="#", encoding="utf-8-sig"
        ).fillna("")
    except Exception as exc:  # pandas raises several parser error types
        kind = "tab-separated" if separator == "\t" else "comma-separated"
        raise ConfigError(
            f"recordings: cannot read sheet {path} ({exc}); a {path.suffix} sheet must be {kind}"
        ) from exc
    if "path" not in sheet.columns:
        raise ConfigError(
            f"recordings: sheet {path} needs a 'path' column (has {list(sheet.columns)})"
        )
    entries = []
    for i, row in sheet.iterrows():
        if not row["path"].strip():
            continue
        rec_path = Path(row["path"].strip())
        if not rec_path.is_absolute():
            rec_path = path.parent / rec_path
        entry: dict[str, Any] = {"path": str(rec_path)}
        for key in ("outdir", "session"):
            if row.get(key, "").strip():
                entry[key] = row[key].strip()
        if row.get("import_format", "").strip():
            spec: dict[str, Any] = {"format": row["import_format"].strip()}
            files = row.get("import_files", "").strip()
            if files:
                pairs = [p.split("=", 1) for p in files.split(";") if p.strip()]
                if all(len(p) == 2 for p in pairs):
                    spec["files"] = {k.strip(): v.strip() for k, v in pairs}
                elif len(pairs) == 1:
                    spec["files"] = files
                else:
                    raise ConfigError(
                        f"recordings: {path} row {i + 2}: import_files must be "
                        "one file or 'view=file' pairs separated by ';'"
                    )
            entry["import"] = spec
        entries.append(entry)
    return entries
