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
    """``err``'s text on one line (whitespace runs collapsed), at most ``limit``
    characters: for quoting a library's message inside a flylib error."""
    return " ".join(str(err).split())[:limit]
