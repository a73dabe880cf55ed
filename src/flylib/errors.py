"""User-facing errors: one line that names the offending file or key and the fix."""

from __future__ import annotations


class FlylibError(Exception):
    """Base class for errors a user can act on (bad config, footage, weights, results)."""


class ConfigError(FlylibError, ValueError):
    """A config value is missing, unknown, of the wrong type or inconsistent."""


class FootageError(FlylibError, ValueError):
    """Footage is missing, unreadable, corrupt or inconsistent across cameras."""


class WeightsError(FlylibError, RuntimeError):
    """Detector weights are missing, unreachable or do not fit the network."""


class ResultsError(FlylibError, ValueError):
    """A results or stage-artifact file is missing, of the wrong version or incomplete."""


class ImportFormatError(FlylibError, ValueError):
    """A 2D-keypoint or calibration file from another tool cannot be used as given."""


class OutputError(FlylibError, OSError):
    """An output cannot be written: the disk is full, a file-size limit is hit, or
    another run holds the output directory's lock."""


class StageError(FlylibError, RuntimeError):
    """A numerical stage (bundle adjustment, pictorial structures, triangulation,
    refinement, kinematics) cannot solve a recording's data as given."""


def one_line(err: BaseException | str, limit: int = 300) -> str:
    """``err``'s text on one line (whitespace collapsed), cut at ``limit`` characters."""
    return " ".join(str(err).split())[:limit]


def did_you_mean(name: object, known: object) -> str:
    """``"did you mean 'x'? "`` for the entry of ``known`` closest to ``name`` (a likely
    typo, :func:`difflib.get_close_matches`), else ``""``: the start of a fix hint."""
    import difflib

    names = [str(k) for k in known]  # type: ignore[union-attr]
    match = difflib.get_close_matches(str(name), names, n=1, cutoff=0.6)
    return f"did you mean {match[0]!r}? " if match else ""


def unknown_key(kind: str, name: object, known: object) -> str:
    """``"unknown <kind>; did you mean 'x'? (known: ...)"``: an unknown-key problem's text."""
    names = [str(k) for k in known]  # type: ignore[union-attr]
    return f"unknown {kind}; {did_you_mean(name, names)}(known: {', '.join(names)})"
