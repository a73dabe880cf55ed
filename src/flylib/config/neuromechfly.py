"""The typed view of the ``neuromechfly`` table (NeuroMechFly joint angles)."""

from __future__ import annotations

from dataclasses import dataclass

from .checks import boolean, integer, number, param


@dataclass(frozen=True)
class NeuromechflyParams:
    """The ``neuromechfly`` table (:mod:`flylib.neuromechfly`).

    Attributes
    ----------
    still_tolerance
        The most the thorax-coxa points may move (95th percentile of their distance from their
        median position, in model leg lengths) before a recording is refused as untethered.
    frame_rate
        Frames per second: the ``time`` column of ``joint_angles.csv`` and the replay's timestep.
    iterations
        Levenberg-Marquardt steps per (frame, leg).
    allow_mirrored
        Fit a 3D that is the fly's mirror image anyway (:mod:`flylib.handedness`); by default such a
        result is refused, naming its cause.
    """

    still_tolerance: float = param(0.1, number(0, exclusive=True), kind=float)
    frame_rate: float = param(100.0, number(0, exclusive=True), kind=float)
    iterations: int = param(20, integer(1))
    allow_mirrored: bool = param(False, boolean, track_default=False)
