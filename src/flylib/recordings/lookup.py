"""Where a listed recording path is looked up: wildcard patterns, and the one-line error for a path
that finds nothing (the closest existing folder, or the config file's folder when the path is there
instead)."""

from __future__ import annotations

import difflib
import glob
import os
import re
from pathlib import Path

from ..errors import ConfigError

_GLOB_CHARS = re.compile(r"[*?\[]")


def is_pattern(text: str | Path) -> bool:
    """Whether a listed path is a wildcard pattern: it holds ``*``, ``?`` or ``[`` and names no
    existing file or folder (a folder named ``fly[1]`` is that folder)."""
    expanded = os.path.expanduser(str(text))
    return bool(_GLOB_CHARS.search(expanded)) and not os.path.lexists(expanded)


def _close_path(path: Path) -> Path | None:
    """An existing directory whose name differs from ``path`` by a likely typo, or ``None``: each
    missing component (from the deepest existing ancestor down) is replaced by its closest sibling
    name (:func:`difflib.get_close_matches`)."""
    path = Path(os.path.abspath(path))
    parts = path.parts
    base = Path(parts[0])
    for i, part in enumerate(parts[1:], start=1):
        candidate = base / part
        if candidate.is_dir():
            base = candidate
            continue
        try:
            names = [p.name for p in base.iterdir() if p.is_dir()]
        except OSError:
            return None
        match = difflib.get_close_matches(part, names, n=1, cutoff=0.6)
        if not match:
            return None
        base = base / match[0]
        if i == len(parts) - 1:
            return base
    return None


def check_recording_path(path: str | Path, where: str, config_dir: Path | None = None) -> None:
    """Refuse a listed literal (non-pattern) recording ``path`` from config key ``where`` (e.g.
    ``recordings[0]``) that does not exist or is not a directory: one :class:`ConfigError` line
    naming the key and the path, with the closest existing directory when there is one ("did you
    mean ...?").

    A relative path is read from the working directory (Snakemake's ``--directory``, else where it
    runs), as Snakemake reads every relative path of a config; the message says so, and names
    ``config_dir`` (the listing config file's folder) too when the path exists there instead.
    """
    path = Path(path)
    if path.is_dir():
        return
    if path.exists():
        raise ConfigError(
            f"{where}: {path} is a file, not a directory; list the folder that "
            "holds the recording's footage"
        )
    close = _close_path(path)
    hint = f"did you mean {close}?" if close is not None else "fix the path"
    if path.is_absolute():
        raise ConfigError(f"{where}: {path} does not exist; {hint}")
    raise ConfigError(f"{where}: {path} does not exist {relative_lookup(path, config_dir, hint)}")


#: How a relative path in a config is read, said in every message about one.
RELATIVE_RULE = (
    "relative paths in a config are read from the working directory, snakemake --directory "
    "or where snakemake runs, as Snakemake reads them; never from the config file's folder"
)


def relative_lookup(path: Path | str, config_dir: Path | None, hint: str) -> str:
    """The end of a message about a relative ``path`` that found nothing
    (``"in the working directory ..."``): where it was looked up, the rule, and whether it exists in
    the config file's folder instead (with the two fixes), else ``hint``."""
    cwd = Path.cwd()
    beside = None
    if config_dir is not None and Path(config_dir).absolute() != cwd:
        beside = Path(config_dir).absolute() / path
    looked = f"in the working directory {cwd} ({RELATIVE_RULE})"
    pattern = is_pattern(str(path))
    if beside is not None and (glob.glob(str(beside)) if pattern else beside.exists()):
        there = (
            "it matches in the config file's folder"
            if pattern
            else "it is in the config file's folder"
        )
        return (
            f"{looked}; {there} ({beside}): list it as {beside}, "
            f"or run from {Path(config_dir).absolute()} (snakemake --directory "
            f"{Path(config_dir).absolute()})"
        )
    if beside is not None:
        looked += f", nor in the config file's folder {Path(config_dir).absolute()}"
    return f"{looked}; {hint}"
