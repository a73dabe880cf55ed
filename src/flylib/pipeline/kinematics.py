"""The kinematics stage: ``results.h5`` -> ``kinematics.h5``, ``angles.csv``, ``angles.png``.

``angles.csv`` follows Anipose's ``angles`` output: one column per angle, named as configured,
in degrees, then ``fnum`` (the frame number), no index column, empty where a point is missing.

``kinematics.h5`` holds ``attrs["meta"]`` (format version, ``stage: kinematics``) and
``kinematics/`` with ``angles`` ``(T, A)``, ``points3d_body`` ``(T, P, 3)``, ``body_rotation``
(``(3, 3)`` world -> body rows x, y, z, or ``(T, 3, 3)``), ``body_origin`` (``(3,)`` or
``(T, 3)``) and attributes ``angle_names``, ``definitions`` (``name -> [a, b, c]``),
``point_names`` and ``tethered`` (JSON).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config.postprocessing import KinematicsParams
from ..kinematics import FILES, Kinematics, compute_kinematics as kinematics_of
from ..paths import atomic_path
from ..stages import Stage
from .inputs import SkeletonSpec, StageInputs, register

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

    from ..config import Config
    from ..skeleton import Skeleton

RECORD = Stage(
    "kinematics",
    default_on=True,
    after=("assemble",),
    needs_one_of=("triangulation", "pictorial_structures"),
    params=KinematicsParams,
    outputs=FILES,
    hint="check the 3D in results.h5 (flylib inspect), or set pipeline.do_kinematics: false",
    memory=(130, 105),
)

STAGE = RECORD.name


@dataclass(frozen=True)
class KinematicsRuntime:
    """The untracked order of the configured angles and segments: ``angles.csv``'s column
    order (the tracked params sort them, so reordering re-runs nothing). ``None``: the
    defaults' order, or sorted."""

    angles: tuple[str, ...] | None = None
    segments: tuple[str, ...] | None = None


@register
@dataclass(frozen=True)
class KinematicsInputs(StageInputs):
    """What the kinematics stage reads."""

    STAGE = STAGE  # not a field: the base declares it a ClassVar

    kinematics: KinematicsParams
    skeleton: SkeletonSpec
    runtime: KinematicsRuntime = KinematicsRuntime()

    @classmethod
    def from_config(cls, config: Config) -> KinematicsInputs:
        params = config.kinematics
        return cls(
            kinematics=params,
            skeleton=SkeletonSpec.from_config(config),
            runtime=KinematicsRuntime(
                angles=tuple(params.angles) if params.angles is not None else None,
                segments=tuple(params.segments) if params.segments is not None else None,
            ),
        )


def compute_kinematics(
    inputs: KinematicsInputs, pts3d: Float[np.ndarray, "T P 3"], skeleton: Skeleton
) -> Kinematics:
    """:func:`flylib.kinematics.compute_kinematics` as ``inputs.kinematics`` says. ``pts3d``:
    world points, NaN = missing; ``skeleton`` names the P axis (``results.h5``'s)."""
    params, order = inputs.kinematics, inputs.runtime
    return kinematics_of(
        pts3d,
        skeleton,
        angles=_in_order(params.angles, order.angles),
        segments=_in_order(params.segments, order.segments),
        tethered=params.tethered,
        body_frame_points=params.body_frame,
    )


def _in_order(table: Mapping | None, order: tuple[str, ...] | None) -> Mapping | None:
    """``table`` back in the config's order (the runtime's; the tracked JSON sorts it)."""
    return table if table is None or order is None else {name: table[name] for name in order}


def write_angles_csv(path: str | Path, kin: Kinematics) -> Path:
    """Write ``angles.csv`` atomically, byte for byte as pandas' ``to_csv(index=False)`` would
    (each value's ``str``, NaN empty) without importing pandas."""
    import csv

    columns = {name: kin.angles[:, k] for k, name in enumerate(kin.angle_names)}
    columns["fnum"] = np.arange(kin.angles.shape[0])
    text = []
    for values in columns.values():
        cells = values.astype(str)
        cells[np.isnan(values)] = ""
        text.append(cells)
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as file:
        writer = csv.writer(file, lineterminator="\n")
        writer.writerow(columns)
        writer.writerows(zip(*text, strict=True))
    return Path(path)


def write_kinematics_h5(path: str | Path, kin: Kinematics, point_names, tethered: bool) -> Path:
    """Write ``kinematics.h5`` atomically (layout in the module docstring)."""
    from ..results import write_analysis

    arrays = {
        "angles": kin.angles,
        "points3d_body": kin.points3d_body,
        "body_rotation": kin.rotation,
        "body_origin": kin.origin,
    }
    attrs = {
        "angle_names": kin.angle_names,
        "definitions": kin.definitions,
        "point_names": list(point_names),
        "tethered": bool(tethered),
    }
    return write_analysis(path, "kinematics", arrays, attrs)


def angles_figure(
    kin: Kinematics,
    path: str | Path,
    *,
    fps: float | None = None,
    dpi: int = 90,
    point_names: Sequence[str] | None = None,
) -> Path:
    """Write angles.png: :func:`angles_plot` saved atomically to ``path``."""
    fig = angles_plot(kin, fps=fps, dpi=dpi, point_names=point_names)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def angles_plot(
    kin: Kinematics,
    *,
    fps: float | None = None,
    dpi: int = 90,
    point_names: Sequence[str] | None = None,
):
    """A matplotlib Figure, one panel per leg (names ``<leg>_...``): flexion angles solid,
    segment yaw/pitch/roll dashed, one colour per angle kind in a legend beside the panels.
    Panels follow ``point_names`` (a leg's first measured point, so the fly reads lf, lm, lh /
    rf, rm, rh), else ``kin.angle_names``' order; never alphabetical."""
    from matplotlib.figure import Figure

    groups: dict[str, list[int]] = {}
    for k, name in enumerate(kin.angle_names):
        groups.setdefault(name.split("_")[0], []).append(k)
    if point_names is not None:
        place = {name: i for i, name in enumerate(point_names)}

        def first_point(item: tuple[str, list[int]]) -> int:
            names = (n for k in item[1] for n in kin.definitions.get(kin.angle_names[k], ()))
            return min((place[n] for n in names if n in place), default=len(place))

        groups = dict(sorted(groups.items(), key=first_point))  # stable: ties keep their order
    n = max(len(groups), 1)
    cols = min(n, 3)
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(5 * cols, 3 * rows), dpi=dpi, layout="constrained")
    t = np.arange(kin.angles.shape[0])
    xlabel = "frame"
    if fps:
        t, xlabel = t / fps, "time (s)"
    # one colour per angle kind, named once beside the panels (inside, it covered traces)
    kinds = list(
        dict.fromkeys(kin.angle_names[k][len(leg) + 1 :] for leg, cs in groups.items() for k in cs)
    )
    colors = {kind: f"C{j % 10}" for j, kind in enumerate(kinds)}
    handles = {}
    for i, (leg, columns) in enumerate(groups.items()):
        ax = fig.add_subplot(rows, cols, i + 1)
        for k in columns:
            kind = kin.angle_names[k][len(leg) + 1 :]
            style = "-" if kind.endswith("flex") else "--"
            (line,) = ax.plot(t, kin.angles[:, k], style, lw=1.2, color=colors[kind], label=kind)
            handles.setdefault(kind, line)
        ax.set_title(leg)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("degrees")
    if handles:
        fig.legend([handles[kind] for kind in kinds], kinds, loc="outside right upper", fontsize=8)
    if not groups:
        fig.add_subplot(1, 1, 1).text(0.5, 0.5, "no angles configured", ha="center")
    fig.suptitle("joint angles (kinematics)")
    return fig


def results_3d(results_path: str | Path, stage: str, *, allow_mirrored: bool = False):
    """The :class:`~flylib.results.PoseResult` a post-processing ``stage`` reads. ResultsError
    if it holds no 3D, or a mirrored fly (:func:`flylib.handedness.mirrored_refusal`) unless
    ``allow_mirrored``."""
    from ..errors import ResultsError
    from ..handedness import mirrored_refusal
    from ..results import PoseResult

    result = PoseResult.load(results_path)
    if result.pts3d is None:
        raise ResultsError(
            f"{results_path}: holds no 3D points; turn on triangulation "
            f"(or set pipeline.do_{stage}: false)"
        )
    refusal = None if allow_mirrored else mirrored_refusal(result, results_path, stage)
    if refusal:
        raise ResultsError(refusal)
    return result


def run_kinematics(inputs: KinematicsInputs, results_path: str | Path, outdir: str | Path) -> dict:
    """Kinematics of ``results.h5``, written as :data:`FILES` into ``outdir``. ResultsError
    without 3D; StageError if the computation fails on the recording's data."""
    from .stage_helpers import solving

    with solving(STAGE, results_path):
        result = results_3d(results_path, STAGE, allow_mirrored=inputs.kinematics.allow_mirrored)
        outdir = Path(outdir)
        kin = compute_kinematics(inputs, result.pts3d, result.skeleton)
        write_kinematics_h5(
            outdir / FILES[0], kin, result.skeleton.point_names, inputs.kinematics.tethered
        )
        write_angles_csv(outdir / FILES[1], kin)
        angles_figure(kin, outdir / FILES[2], point_names=result.skeleton.point_names)
    return {"angles": kin.angle_names, "frames": int(kin.angles.shape[0])}
