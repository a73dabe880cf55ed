"""Kinematic replay in flygym: drive NeuroMechFly's leg joints with the angles (position control,
the fly tethered in the air, MuJoCo on the CPU, nothing rendered) and read back where the
simulated joints are; :func:`replay_data` reads the stage's ``joint_angles.csv`` as flygym's
replay examples do.

flygym is optional (the ``neuromechfly`` extra): flygym 1.x is the API used here; it pins
``numpy < 2.1`` and ``mujoco 3.2.7``, so it lives in its own environment (2.x needs Python >= 3.12).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import FlylibError, ResultsError
from .model import LEGS, dof_names

if TYPE_CHECKING:  # pragma: no cover
    from pathlib import Path

    from jaxtyping import Float

#: flygym's bodies whose origins are the chain's joints (claw: the ``Tarsus5`` origin).
_BODIES = ("Coxa", "Femur", "Tibia", "Tarsus1", "Tarsus5")


def flygym_unavailable() -> str | None:
    """Why flygym's replay cannot run here, or ``None`` when it can."""
    try:
        import flygym
    except ImportError as error:
        return (
            f"flygym is not installed ({error}); pip install 'flygym<2' in an environment "
            "with numpy < 2.1 (flygym 2.x needs Python >= 3.12)"
        )
    if not hasattr(flygym, "SingleFlySimulation"):
        return (
            f"flygym {getattr(flygym, '__version__', '?')} lacks the 1.x API (SingleFlySimulation)"
        )
    return None


def replay_angles(
    angles: Float[np.ndarray, "T 42"],
    frame_rate: float,
    *,
    timestep: float = 1e-4,
    settle: float = 0.05,
) -> Float[np.ndarray, "T 6 5 3"]:
    """Run flygym's NeuroMechFly through the recording's angles: the simulated ThC, CTr, FTi,
    TiTa and claw of each leg at each frame's time, in the model's thorax frame (mm).

    ``angles``: radians, columns :func:`~flylib.neuromechfly.model.dof_names`; a NaN holds the
    joint's last finite target (zero before the first). The targets are linearly interpolated
    from ``frame_rate`` (frames per second) to MuJoCo's ``timestep`` (seconds); ``settle`` seconds
    hold the first frame's angles before the replay (the model starts stretched out). A
    FlylibError (with the reason) if flygym cannot run here."""
    reason = flygym_unavailable()
    if reason:
        raise FlylibError(f"NeuroMechFly replay: {reason}")
    from flygym import Fly, SingleFlySimulation
    from flygym.arena import Tethered

    targets = _held(np.asarray(angles, dtype=np.float64))
    n_frames = targets.shape[0]
    fly = Fly(actuated_joints=dof_names(), control="position", init_pose="stretch")
    sim = SingleFlySimulation(fly=fly, cameras=[], arena=Tethered(), timestep=timestep)
    sim.reset()
    for _ in range(int(round(settle / timestep))):
        sim.step({"joints": targets[0]})
    named = sim.physics.named.data
    names = [[f"{fly.name}/{leg}{body}" for body in _BODIES] for leg in LEGS]
    frame_times = np.arange(n_frames) / float(frame_rate)
    steps = int(round(frame_times[-1] / timestep)) + 1 if n_frames > 1 else 1
    step_times = np.arange(steps) * timestep
    interpolated = np.stack(
        [np.interp(step_times, frame_times, targets[:, j]) for j in range(targets.shape[1])], -1
    )
    record_at = np.searchsorted(step_times, frame_times - timestep / 2)
    out = np.full((n_frames, len(LEGS), len(_BODIES), 3), np.nan)
    frame = 0
    for step in range(steps):
        sim.step({"joints": interpolated[step]})
        while frame < n_frames and record_at[frame] == step:
            origin = np.asarray(named.xpos[f"{fly.name}/Thorax"])
            to_body = np.asarray(named.xmat[f"{fly.name}/Thorax"]).reshape(3, 3)
            world = np.array([[named.xpos[n] for n in leg] for leg in names])
            out[frame] = (world - origin) @ to_body
            frame += 1
    sim.close()
    return out


def _held(angles: np.ndarray) -> np.ndarray:
    held = angles.copy()
    last = np.zeros(angles.shape[1])
    for t in range(held.shape[0]):
        finite = np.isfinite(held[t])
        last = np.where(finite, held[t], last)
        held[t] = last
    return held


def replay_residuals(
    angles: Float[np.ndarray, "T 42"],
    measured: Float[np.ndarray, "T 6 5 3"],
    frame_rate: float,
    **options,
) -> dict[str, dict[str, float]]:
    """Replay ``angles`` (:attr:`NmfAngles.angles <flylib.neuromechfly.NmfAngles>`) in flygym
    (``options`` to :func:`replay_angles`) and compare the simulated joints with the ``measured``
    aligned legs (:attr:`NmfAngles.aligned`) and with the model's forward kinematics of the same
    angles: ``{"vs_measured": {...}, "vs_model": {...}}``, each the ``median``, ``p95`` and ``max``
    distance in model leg lengths over every finite (frame, leg, joint)."""
    from .model import forward_kinematics, leg_lengths

    simulated = replay_angles(angles, frame_rate, **options)
    lengths = leg_lengths()[None, :, None]
    out = {}
    for key, reference in (("vs_measured", measured), ("vs_model", forward_kinematics(angles))):
        distance = np.linalg.norm(simulated - reference, axis=-1) / lengths
        finite = distance[np.isfinite(distance) & np.isfinite(angles).all(axis=1)[:, None, None]]
        out[key] = {
            "median": float(np.median(finite)),
            "p95": float(np.percentile(finite, 95)),
            "max": float(finite.max()),
        }
    return out


def replay_data(path: str | Path) -> dict:
    """``joint_angles.csv`` as flygym's kinematic replay reads it: ``{"meta": {"timestep":
    seconds}, "joint_<leg><dof>": (T,) radians, ...}``; a ResultsError if a column is missing."""
    import pandas as pd

    table = pd.read_csv(path)
    missing = [c for c in ("time", *dof_names()) if c not in table.columns]
    if missing:
        raise ResultsError(
            f"{path}: not a NeuroMechFly angles table (missing columns {', '.join(missing[:3])}"
            f"{' ...' if len(missing) > 3 else ''}); re-run the neuromechfly stage"
        )
    time = table["time"].to_numpy(dtype=np.float64)
    timestep = float(np.median(np.diff(time))) if time.size > 1 else 1.0
    data: dict = {"meta": {"timestep": timestep}}
    for name in dof_names():
        data[name] = table[name].to_numpy(dtype=np.float64)
    return data
