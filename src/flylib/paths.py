"""Per-user locations flylib writes outside a run's output directory."""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from pathlib import Path


def cache_dir() -> Path:
    """The per-user cache (detector weights, compiled JAX kernels).

    ``$FLYLIB_CACHE`` when set, else ``~/.cache/flylib``.
    """
    env = os.environ.get("FLYLIB_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "flylib"


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``path``; rename it to ``path`` on success.

    The temporary file lives in the same directory (so the final ``os.replace`` is
    atomic), keeps ``path``'s suffix (FFmpeg and pandas pick the format from it) and is
    removed if the block raises, leaving any previous ``path`` untouched: a crash never
    leaves a truncated output under the final name. The parent directory is created
    if missing.

    Parameters
    ----------
    path
        The final destination.

    Yields
    ------
    Path
        Where to write; it does not exist yet.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
