"""Files flylib reads or writes outside a run's output directory, and atomic writes."""

from __future__ import annotations

import contextlib
import errno
import functools
import glob
import os
import re
import socket
import unicodedata
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from .locking import claim_lost, pid_alive

#: The packaged default config (the repository's ``config/config.yaml`` is the user's
#: editable copy; a test keeps the two identical).
DEFAULT_CONFIG_PATH = Path(__file__).with_name("default_config.yaml")


def fill_template(template: str, values: dict[str, str], key: str) -> str:
    """A path template with its placeholders filled: only plain ``{name}`` of ``values``.

    ``str.format`` would also evaluate conversions (``{id!r}``), format specs, attribute and
    index access (``{recording.parent}``, ``{id[0]}``); a config's path template may use none
    of them. ``{{`` and ``}}`` are literal braces. ConfigError names ``key`` (the config key
    the template came from), the offending field and the allowed placeholders.
    """
    from string import Formatter

    from .errors import ConfigError

    allowed = ", ".join(f"{{{name}}}" for name in values)
    parts: list[str] = []
    try:
        fields = list(Formatter().parse(template))
    except ValueError as exc:  # a lone { or }
        raise ConfigError(
            f"{key}: {template!r} is not a path template ({exc}); use only the placeholders "
            f"{allowed} (write {{{{ and }}}} for a literal brace)"
        ) from None
    for literal, field, spec, conversion in fields:
        parts.append(literal)
        if field is None:
            continue
        if field not in values or spec or conversion:
            written = (
                "{"
                + field
                + (f"!{conversion}" if conversion else "")
                + (f":{spec}" if spec else "")
                + "}"
            )
            raise ConfigError(
                f"{key}: {written} in {template!r} is not a placeholder; use only "
                f"{allowed}, written plain (e.g. results/{{id}})"
            )
        parts.append(values[field])
    return "".join(parts)


#: What a name keeps as a file name: letters and digits of any script, ``_``, ``.``, ``-``.
_NAME_UNSAFE = re.compile(r"[^\w.-]+")


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a folder name (dots only, a path separator, a control
    character), or ``None``."""
    if not name.strip("."):
        return "it is made of dots only (. and .. are folders that exist)"
    if "/" in name or "\\" in name:
        return "it holds a path separator (/ or \\)"
    if any(unicodedata.category(c) == "Cc" for c in name):
        return "it holds a control character"
    return None


def file_name(name: str, fallback: str) -> str:
    """``name`` (NFC) as one file name: each run of other ASCII characters becomes ``_``,
    any other character its code point (``u1f41d``); ``fallback`` when nothing is left."""

    def encode(run: re.Match) -> str:
        codes = "".join("_" if c.isascii() else f"_u{ord(c):04x}_" for c in run.group())
        return re.sub("_+", "_", codes)

    safe = _NAME_UNSAFE.sub(encode, unicodedata.normalize("NFC", name)).strip("_")
    return safe if safe.strip(".") else fallback


def cache_dir() -> Path:
    """The per-user cache (weights, JAX kernels): ``$FLYLIB_CACHE``, else ``~/.cache/flylib``."""
    env = os.environ.get("FLYLIB_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "flylib"


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a new temporary sibling of ``path``; rename it to ``path`` on success.

    The temporary file lives in the same directory (so ``os.replace`` is atomic), keeps
    ``path``'s suffix (FFmpeg and pandas pick the format from it) and is removed if the block
    raises, leaving any previous ``path`` untouched. The parent directory is created if
    missing; temporary files of ``path`` left by dead writers on this host are removed first
    (:func:`remove_stale_temps`). Inside a run's job, the file is renamed into place only
    while the run still holds the output directory's claim
    (:func:`flylib.locking.claim_lost`).

    OutputError (nothing kept) when the write runs out of space (disk full, quota, file-size
    limit), when ``path`` cannot be created (:func:`cannot_write`) or another run took the
    output directory over meanwhile.
    """
    path = Path(path)
    tmp = _new_temp(path)
    try:
        yield tmp
        lost = claim_lost(path)
        if lost is not None:
            from .errors import OutputError

            raise OutputError(lost)
        try:
            os.replace(tmp, path)
        except OSError as err:
            raise cannot_write(path, err) from None
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


_HOST = socket.gethostname()


def _new_temp(path: Path) -> Path:
    """A name for a temporary sibling of ``path``, once its folder (created if missing) has
    taken a file of that name; :func:`cannot_write` when it cannot."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path.parent, of=path)
        tmp = path.with_name(
            f".{path.stem}.{os.getpid()}@{_HOST}.{uuid.uuid4().hex[:8]}.tmp{path.suffix}"
        )
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        tmp.unlink()
    except OSError as err:
        raise cannot_write(path, err) from None
    return tmp


def cannot_write(path: str | Path, err: OSError):
    """The :class:`~flylib.errors.OutputError` saying in one line why ``path`` cannot be written."""
    from .errors import OutputError, one_line

    path = Path(path)
    above = next((p for p in path.parents if os.path.lexists(p)), None)
    if above is not None and not above.is_dir():
        reason = f"{above} is a file, not a folder"
    elif isinstance(err, FileNotFoundError):
        reason = f"its folder {path.parent} does not exist"
    else:
        reason = (err.strerror or one_line(err)).lower()
    return OutputError(f"{path}: cannot be written ({reason}); nothing was written")


#: The file in a folder listing the files flylib wrote (or, for a workflow output folder,
#: owns) there, one name per line relative to the folder (:func:`written_by_flylib`).
OUTPUTS_MANIFEST = ".flylib-outputs"


def recorded_outputs(folder: str | Path) -> set[str] | None:
    """The names in ``folder``'s :data:`OUTPUTS_MANIFEST` (``None``: it has none)."""
    try:
        text = (Path(folder) / OUTPUTS_MANIFEST).read_text(encoding="utf-8")
    except (FileNotFoundError, NotADirectoryError):
        return None
    except (OSError, UnicodeDecodeError):
        return set()
    return {line for line in text.splitlines() if line}


def record_outputs(folder: str | Path, names: Iterable[str]) -> None:
    """Add ``names`` (relative to ``folder``) to its :data:`OUTPUTS_MANIFEST`, atomically."""
    folder = Path(folder)
    known = recorded_outputs(folder) or set()
    new = known | {str(n) for n in names}
    if new == known and (folder / OUTPUTS_MANIFEST).exists():
        return
    with atomic_path(folder / OUTPUTS_MANIFEST) as tmp:
        tmp.write_text("".join(f"{n}\n" for n in sorted(new)), encoding="utf-8")


def written_by_flylib(path: str | Path, *, hdf5: bool = False) -> bool:
    """Whether flylib wrote ``path``: its folder's :data:`OUTPUTS_MANIFEST` names it, or
    (``hdf5``) it is an HDF5 file carrying flylib's ``meta`` attribute (a stage artifact or
    ``results.h5`` of any flylib version). Anything else is the user's."""
    path = Path(path)
    if path.name in (recorded_outputs(path.parent) or ()):
        return True
    return hdf5 and is_flylib_hdf5(path)


def is_flylib_hdf5(path: str | Path) -> bool:
    """Whether ``path`` is an HDF5 file whose ``meta`` attribute flylib wrote."""
    import json

    try:
        with open(path, "rb") as f:
            if f.read(8) != b"\x89HDF\r\n\x1a\n":
                return False
        import h5py

        with h5py.File(path, "r") as f:
            meta = json.loads(f.attrs["meta"])
    except (OSError, KeyError, ValueError, TypeError, RuntimeError):
        return False
    return isinstance(meta, dict) and "deeperfly_format_version" in meta


def real_paths() -> Callable[[str | Path], str]:
    """:func:`os.path.realpath` for many files in few folders: each folder is resolved once (a file
    that is itself a link, whole), not one ``lstat`` per path component per file."""
    folder = functools.lru_cache(maxsize=None)(os.path.realpath)

    def real(path: str | Path) -> str:
        head, name = os.path.split(os.fspath(path))
        if name in ("", ".", "..") or os.path.islink(path):
            return os.path.realpath(path)
        return os.path.join(folder(head or "."), name)

    return real


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether ``a`` and ``b`` are one file: the same resolved path, or (both existing) the
    same inode, so a link or a second name of a file counts as that file."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def refuse_overwrite(
    path: str | Path, inputs: dict[str, str], role: str, *, force: bool = False
) -> None:
    """Refuse (OutputError) to write ``path`` over an input, over a file flylib did not write,
    or where it cannot be written (its folders are created).

    ``inputs`` maps each input file to its role (e.g. ``"the input RESULTS_H5"``); ``role``
    is what would write ``path`` (e.g. ``"--csv3d"``). ``force`` replaces an existing file
    flylib did not write (never an input). Only a file an earlier export recorded
    (:data:`OUTPUTS_MANIFEST`) is flylib's here: another recording's ``results.h5`` is not
    replaced without ``force`` either.
    """
    from .errors import OutputError

    for source, what in inputs.items():
        if same_file(path, source):
            raise OutputError(
                f"{path} is {what} and would be overwritten by {role}; write to another file"
            )
    if not force and os.path.lexists(path) and not written_by_flylib(path):
        raise OutputError(
            f"{path} exists and was not written by flylib; {role} would replace it: "
            "choose another file, or pass --force to replace it"
        )
    _new_temp(Path(path))


# atomic_path's temporary names: .<stem>.<pid>@<host>.<8 hex>.tmp<suffix> (a name without
# @<host> is taken as this host's).
_TEMP_NAME = re.compile(
    r"^\.(?P<stem>.*)\.(?P<pid>\d+)(?:@(?P<host>[^/]+?))?\.[0-9a-f]{8}\.tmp(?P<suffix>\.[^.]*)?$"
)


def _stale_temp(path: str | Path) -> bool:
    """Whether ``path`` is a temporary file of :func:`atomic_path` whose writer is gone (only
    writers on this host can be told dead: another host's temporary file is never stale)."""
    match = _TEMP_NAME.match(Path(path).name)
    if match is None:
        return False
    host = match.group("host")
    if host is not None and host != _HOST:
        return False
    return not pid_alive(int(match.group("pid")))


def remove_stale_temps(
    directory: str | Path, *, of: str | Path | None = None, recursive: bool = False
) -> list[Path]:
    """Remove (and return) the temporary files that killed writers left in ``directory``.

    A writer killed mid-write (``kill -9``, out of memory) cannot remove its temporary file;
    the next write of the same file, and the workflow when it claims an output directory,
    remove those whose writer (this host, its pid) no longer exists. A missing ``directory``
    holds nothing; ``of`` limits the search to the temporary files of that final path.
    """
    directory = Path(directory)
    if of is not None:
        of = Path(of)
        pattern = f".{glob.escape(of.stem)}.*.tmp{glob.escape(of.suffix)}"
    else:
        pattern = ".*.tmp*"
    try:
        candidates = list(directory.rglob(pattern) if recursive else directory.glob(pattern))
    except OSError:
        return []
    removed = []
    for candidate in candidates:
        match = _TEMP_NAME.match(candidate.name)
        if match is None or (of is not None and match.group("stem") != of.stem):
            continue
        if _stale_temp(candidate) and candidate.is_file():
            with contextlib.suppress(FileNotFoundError):
                candidate.unlink()
                removed.append(candidate)
    return removed


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
