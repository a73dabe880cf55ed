"""The typed view of the ``neuromechfly`` table (NeuroMechFly joint angles)."""

from __future__ import annotations

from dataclasses import dataclass

from .checks import _integer, _number, _param


@dataclass(frozen=True)
class NeuromechflyParams:
    """The ``neuromechfly`` table (:mod:`flylib.neuromechfly`).

    Attributes
    ----------
    still_tolerance
        The most the thorax-coxa points may move (95th percentile of their distance
        from their median position, in model leg lengths) before a recording is
        refused as untethered.
    frame_rate
        Frames per second: the ``time`` column of ``joint_angles.csv`` and the
        replay's timestep.
    iterations
        Levenberg-Marquardt steps per (frame, leg).
    """

    still_tolerance: float = _param(0.1, _number(0, exclusive=True), kind=float)
    frame_rate: float = _param(100.0, _number(0, exclusive=True), kind=float)
    iterations: int = _param(20, _integer(1))
