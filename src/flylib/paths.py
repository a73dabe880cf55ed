"""Files flylib reads or writes outside a run's output directory, and atomic writes."""

from __future__ import annotations

import contextlib
import errno
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

#: The packaged default config, a real file inside the package (the repository's
#: ``config/config.yaml`` is the user's editable copy; a test keeps the two identical).
DEFAULT_CONFIG_PATH = Path(__file__).with_name("default_config.yaml")


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

    Raises
    ------
    OutputError
        When the write fails for want of space (disk full, quota, file-size limit):
        one line naming ``path`` and saying that nothing was kept.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except (OSError, RuntimeError) as err:  # h5py's close after a failed write: RuntimeError
        cause = out_of_space(err)
        if cause is None:
            raise
        from .errors import OutputError

        previous = "the previous file is unchanged" if path.exists() else "no partial file is left"
        raise OutputError(
            f"{path}: could not be written ({_reason(cause)}); nothing was kept ({previous}); "
            "free disk space or raise the file-size limit and re-run"
        ) from None
    finally:
        tmp.unlink(missing_ok=True)


_NO_SPACE = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT}


def out_of_space(err: BaseException | None) -> BaseException | None:
    """The error in ``err``'s chain that says a write ran out of space, if any
    (HDF5 reports the system's error text inside its own message)."""
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if getattr(err, "errno", None) in _NO_SPACE or any(
            os.strerror(c) in str(err) for c in _NO_SPACE
        ):
            return err
        err = err.__cause__ or err.__context__
    return None


def _reason(err: BaseException) -> str:
    if getattr(err, "errno", None) in _NO_SPACE:
        return os.strerror(err.errno)
    text = " ".join(str(err).split())
    for code in _NO_SPACE:
        if os.strerror(code) in text:
            return os.strerror(code)
    return text
