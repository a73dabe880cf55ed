"""Footage matching: one directory's footage files per source (:func:`find_recording`), one
extension shared by every source, naturally sorted, with equal frame counts."""

from __future__ import annotations

import glob
import logging
import os
import stat
from collections.abc import Iterable, Mapping
from pathlib import Path

from ..errors import FootageError
from ..io.base import IMAGE_EXTS, VIDEO_EXTS
from ..io.images import natural_key, sequence_gap
from .frame_counts import video_frame_count

log = logging.getLogger(__name__)

FOOTAGE_EXTS = VIDEO_EXTS | IMAGE_EXTS


def natural_sorted(paths: Iterable[Path]) -> list[Path]:
    """``paths`` sorted by :func:`natural_key` of their names (then full path)."""
    return sorted(paths, key=lambda p: (natural_key(Path(p).name), str(p)))


def footage_matches(directory: Path, pattern: str) -> list[Path]:
    """Footage files (video or image extensions) matching ``pattern`` in ``directory``; a match with
    a footage extension that is no regular file (a FIFO, a device, a link to one or to nothing) is a
    :class:`FootageError` saying what it is."""
    hits = [Path(p) for p in glob.glob(os.path.join(glob.escape(str(directory)), pattern))]
    hits = [p for p in hits if p.suffix.lower() in FOOTAGE_EXTS and not p.is_dir()]
    for path in hits:
        if not path.is_file():
            raise FootageError(f"{path}: {_not_a_file(path)}; replace it with the footage file")
    return hits


def _not_a_file(path: Path) -> str:
    """What ``path`` (not a regular file) is, in words: ``"is a named pipe (FIFO), not a ..."``."""
    link = f"a link to {os.path.realpath(path)}, " if path.is_symlink() else ""
    try:
        mode = path.stat().st_mode
    except OSError:
        return f"is {link}which does not exist" if link else "cannot be read"
    kinds = [
        (stat.S_ISFIFO, "a named pipe (FIFO)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ]
    kind = next((text for test, text in kinds if test(mode)), "not a regular file")
    return f"is {link}{kind}, not a video or image file"


def _pick_extension(per_source: dict[str, list[Path]]) -> str | None:
    """One footage extension every source has, preferring videos (cheapest to decode)."""
    common: set[str] | None = None
    for files in per_source.values():
        exts = {p.suffix.lower() for p in files}
        common = exts if common is None else common & exts
    if not common:
        return None
    return sorted(common, key=lambda e: (e not in VIDEO_EXTS, e))[0]


def find_recording(
    directory: str | Path,
    patterns: Mapping[str, str],
    *,
    check_frames: bool = True,
    strict: bool = False,
) -> dict[str, list[Path]] | None:
    """Resolve one directory to its ``source -> footage files`` map, or ``None`` when it is not a
    valid recording (the reason logged as a warning, or raised as
    :class:`~flylib.errors.FootageError` with ``strict``).

    Each source's pattern (``patterns``: source name -> footage glob in ``[[sources]]`` order,
    :func:`flylib.config.sources.patterns_of`) is matched inside ``directory``; the matches are
    reduced to one footage extension shared by every source (videos preferred), naturally sorted,
    and checked: a video source holds exactly one file, and with ``check_frames`` every source has
    the same frame count (video container counts, image-sequence lengths).
    """
    directory = Path(directory)

    def reject(reason: str) -> None:
        if strict:
            raise FootageError(reason)
        log.warning("skipping %s: %s", directory, reason)

    if not directory.is_dir():
        reject(f"{directory}: is not a directory")
        return None
    try:
        matched = {name: footage_matches(directory, pat) for name, pat in patterns.items()}
    except FootageError as exc:
        reject(str(exc))
        return None
    missing = [f"{name} ({patterns[name]!r})" for name, files in matched.items() if not files]
    if missing:
        reject(
            f"{directory}: no footage for source(s) {', '.join(missing)}; "
            "a recording needs footage for every configured source"
        )
        return None
    ext = _pick_extension(matched)
    if ext is None:
        reject(
            f"{directory}: the sources share no footage file extension "
            f"({ {n: sorted({p.suffix for p in f}) for n, f in matched.items()} })"
        )
        return None
    sources = {
        n: natural_sorted(p for p in files if p.suffix.lower() == ext)
        for n, files in matched.items()
    }
    gaps = [gap for files in sources.values() if (gap := sequence_gap(files)) is not None]
    if ext not in VIDEO_EXTS and gaps:
        reject(gaps[0])
        return None
    if ext in VIDEO_EXTS:
        several = {n: [p.name for p in f] for n, f in sources.items() if len(f) > 1}
        if several:
            reject(
                f"{directory}: several videos match one source {several}; "
                "make each source's filename pattern match a single video"
            )
            return None
    if check_frames:
        counts = _frame_counts(sources, ext, reject)
        if counts is None:
            return None
        known = {n: c for n, c in counts.items() if c is not None}
        if len(set(known.values())) > 1:
            reject(
                f"{directory}: sources have different frame counts {known}; "
                "every camera must cover the same frames"
            )
            return None
    return sources


def _frame_counts(sources: dict[str, list[Path]], ext: str, reject) -> dict[str, int | None] | None:
    if ext not in VIDEO_EXTS:
        return {n: len(files) for n, files in sources.items()}
    counts: dict[str, int | None] = {}
    for name, files in sources.items():
        try:
            counts[name] = video_frame_count(files[0])
        except FootageError as exc:
            reject(str(exc))
            return None
    return counts
