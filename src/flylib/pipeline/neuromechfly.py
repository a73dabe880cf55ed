"""The neuromechfly stage: ``results.h5`` -> ``neuromechfly.h5``, ``joint_angles.{csv,png}``.

``joint_angles.csv``: one row per frame, ``time`` (seconds, ``frame / frame_rate``), then
flygym's 42 leg joints ``joint_LFCoxa`` ... ``joint_RHTarsus1`` in flygym's order
(``flygym.preprogrammed.all_leg_dofs``), radians, an empty field where a leg was not solved.
:func:`flylib.neuromechfly.replay.replay_data` turns it into the dictionary flygym's
kinematic-replay examples read (``{"meta": {"timestep": dt}, "joint_LFCoxa": (T,) ...}``).

``neuromechfly.h5``: ``attrs["meta"]`` (format version, ``stage: neuromechfly``) and
``neuromechfly/`` with ``angles`` ``(T, 42)`` radians, ``residual`` ``(T, 6, 5)`` (leg lengths;
the fitted chain), ``model_residual`` ``(T, 6, 5)`` (the model's chain), ``aligned``
``(T, 6, 5, 3)`` (model mm), ``similarity_rotation`` ``(3, 3)``, ``similarity_translation``
``(3,)``, ``leg_scale`` ``(6,)``, ``segment_scale`` ``(6, 4)`` and attributes ``dof_names``,
``legs``, ``chain_joints``, ``frame_rate``, ``similarity_scale``, ``thorax_motion``,
``mirrored``, ``unsolved``, ``residual_summary``, ``model_residual_summary`` (JSON).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config.neuromechfly import NeuromechflyParams
from ..neuromechfly import FILES
from ..neuromechfly.model import CHAIN_JOINTS, DOF_SUFFIXES, LEGS, dof_names
from ..paths import atomic_path
from ..stages import Stage
from .inputs import SkeletonSpec, StageInputs, register

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..config import Config
    from ..neuromechfly.angles import NmfAngles
    from ..skeleton import Skeleton

RECORD = Stage(
    "neuromechfly",
    default_on=False,
    after=("kinematics",),
    needs_one_of=("triangulation", "pictorial_structures"),
    params=NeuromechflyParams,
    outputs=FILES,
)

STAGE = RECORD.name


@register
@dataclass(frozen=True)
class NeuromechflyInputs(StageInputs):
    """What the neuromechfly stage reads."""

    STAGE = STAGE  # not a field: the base declares it a ClassVar

    neuromechfly: NeuromechflyParams
    skeleton: SkeletonSpec

    @classmethod
    def from_config(cls, config: Config) -> NeuromechflyInputs:
        return cls(neuromechfly=config.neuromechfly, skeleton=SkeletonSpec.from_config(config))


def angles_table(nmf: NmfAngles, frame_rate: float):
    """The replay table (``pandas.DataFrame``): ``time``, then the 42 joints in radians."""
    import pandas as pd

    table = pd.DataFrame(nmf.angles, columns=dof_names())
    table.insert(0, "time", np.arange(nmf.angles.shape[0]) / float(frame_rate))
    return table


def write_angles_csv(path: str | Path, nmf: NmfAngles, frame_rate: float) -> Path:
    """Write ``joint_angles.csv`` atomically (layout in the module docstring)."""
    with atomic_path(path) as tmp:
        angles_table(nmf, frame_rate).to_csv(tmp, index=False)
    return Path(path)


def write_nmf_h5(path: str | Path, nmf: NmfAngles, frame_rate: float) -> Path:
    """Write ``neuromechfly.h5`` atomically (layout in the module docstring)."""
    from ..results import write_analysis

    a = nmf.alignment
    arrays = {
        "angles": nmf.angles,
        "residual": nmf.residual,
        "model_residual": nmf.model_residual,
        "segment_scale": a.segment_scale,
        "aligned": nmf.aligned,
        "similarity_rotation": a.rotation,
        "similarity_translation": a.translation,
        "leg_scale": a.leg_scale,
    }
    attrs = {
        "dof_names": dof_names(),
        "legs": list(LEGS),
        "chain_joints": list(CHAIN_JOINTS),
        "frame_rate": float(frame_rate),
        "similarity_scale": a.scale,
        "thorax_motion": a.thorax_motion,
        "mirrored": a.mirrored,
        "unsolved": nmf.unsolved,
        "residual_summary": nmf.residual_summary(),
        "model_residual_summary": nmf.residual_summary(model=True),
    }
    return write_analysis(path, "neuromechfly", arrays, attrs)


def angles_figure(nmf: NmfAngles, path: str | Path, *, frame_rate: float, dpi: int = 90) -> Path:
    """One panel per leg: its seven angles (degrees) over time, the median forward-kinematics
    residuals (fitted chain, model's chain) in the title."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 6), dpi=dpi, layout="constrained")
    t = np.arange(nmf.angles.shape[0]) / frame_rate
    per_leg = np.degrees(nmf.angles.reshape(len(t), len(LEGS), len(DOF_SUFFIXES)))
    for k, leg in enumerate(LEGS):
        ax = fig.add_subplot(2, 3, k + 1)
        for j, suffix in enumerate(DOF_SUFFIXES):
            ax.plot(t, per_leg[:, k, j], lw=1.1, label=suffix)
        fitted = nmf.residual[:, k][np.isfinite(nmf.residual[:, k])]
        model = nmf.model_residual[:, k][np.isfinite(nmf.model_residual[:, k])]
        note = (
            f"median FK residual {100 * np.median(fitted):.2f}% of the leg "
            f"(model's chain {100 * np.median(model):.1f}%)"
            if fitted.size
            else "not solved"
        )
        ax.set_title(f"{leg}: {note}", fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("degrees")
        if k == 0:
            ax.legend(fontsize=7, ncol=2, loc="upper right")
    fig.suptitle("NeuroMechFly joint angles (flygym's joints)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def compute_neuromechfly(
    inputs: NeuromechflyInputs,
    pts3d: Float[np.ndarray, "T P 3"],
    skeleton: Skeleton,
    *,
    source: str = "3D",
) -> NmfAngles:
    """:func:`~flylib.neuromechfly.compute_nmf_angles` as ``inputs.neuromechfly`` says.
    ``pts3d``: world points, NaN = missing; ``skeleton`` names the P axis (``results.h5``'s);
    ``source`` names the 3D in messages."""
    from ..neuromechfly.angles import compute_nmf_angles  # JAX: not while the homes are found

    params = inputs.neuromechfly
    return compute_nmf_angles(
        pts3d,
        skeleton,
        still_tolerance=params.still_tolerance,
        iterations=params.iterations,
        source=source,
    )


def run_neuromechfly(
    inputs: NeuromechflyInputs, results_path: str | Path, outdir: str | Path
) -> dict:
    """NeuroMechFly angles of ``results.h5``, written as :data:`FILES` into ``outdir``.
    ResultsError if it holds no 3D, its thorax is not still, or too few thorax-coxa points."""
    from .kinematics import results_3d

    result = results_3d(results_path, STAGE, allow_mirrored=inputs.neuromechfly.allow_mirrored)
    outdir = Path(outdir)
    frame_rate = inputs.neuromechfly.frame_rate
    nmf = compute_neuromechfly(inputs, result.pts3d, result.skeleton, source=str(results_path))
    write_nmf_h5(outdir / FILES[0], nmf, frame_rate)
    write_angles_csv(outdir / FILES[1], nmf, frame_rate)
    angles_figure(nmf, outdir / FILES[2], frame_rate=frame_rate)
    return {
        "frames": int(nmf.angles.shape[0]),
        "unsolved": nmf.unsolved,
        "residual_median": float(np.nanmedian(nmf.residual)),
    }
