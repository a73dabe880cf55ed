"""The workflow's stages: one :class:`Stage` record each, in run order (:data:`REGISTRY`).

Every fact the package keeps about a stage as a whole is a field of its record. The tables
the config, results and workflow layers read (``flylib.config.STAGES``, ``STAGE_DEFAULTS``,
``PARAM_STAGES``, ``flylib.results.ARTIFACTS``, ``STAGE_GROUPS``) are derived from them.

A stage's code lives in its home, ``flylib.pipeline.<stage>``: its inputs class (made known
here by :func:`register` when the home is imported) and ``run_<stage>``, both looked up on
first use, so importing this module imports nothing heavy (JAX, torch): the config and
results layers below the stage homes read it.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module
from typing import Any, TypeVar

__all__ = ["FINAL_3D", "REGISTRY", "SOLVES_3D", "Stage", "by_name", "register", "run_function"]


@dataclass(frozen=True)
class Stage:
    """One workflow stage.

    Attributes
    ----------
    name
        Its rule, its config table, ``pipeline.do_<name>``.
    default_on
        Whether it runs when ``pipeline.do_<name>`` is absent; ``None``: no key toggles it.
    needs_one_of
        Upstream stages it starts from: it runs only while one of them runs (empty: no such
        condition).
    artifact
        Its artifact's file name inside ``<outdir>/stages/``, or ``None``.
    results_group
        Whether it owns a group in ``results.h5`` (assembly copies it from the artifact).
    solves_3d
        Whether it solves a 3D pose (its group holds ``points3d`` and the 2D ``points``).
    hint
        What to check when its numerical step fails on a recording's data (the end of the
        one-line error), or ``None``.
    memory
        ``(fixed MB, MB per million (frame, point, view) elements)``: its job's measured peak
        (``benchmarks/stage_memory.py``), or ``None`` (its rule states a fixed ``mem_mb``).
    """

    name: str
    default_on: bool | None
    needs_one_of: tuple[str, ...] = ()
    artifact: str | None = None
    results_group: bool = False
    solves_3d: bool = False
    hint: str | None = None
    memory: tuple[int, int] | None = None

    @property
    def toggled(self) -> bool:
        """Whether ``pipeline.do_<name>`` turns the stage on and off."""
        return self.default_on is not None

    @property
    def home(self) -> str:
        """The module that defines the stage's inputs class and run function."""
        return f"flylib.pipeline.{self.name}"

    def inputs_class(self) -> type:
        """The stage's :class:`~flylib.pipeline.inputs.StageInputs` class (imports its home)."""
        if self.name not in _INPUTS:
            import_module(self.home)
        return _INPUTS[self.name]

    def run_function(self) -> Any:
        """``run_<name>`` of the stage's home (importing it on first use)."""
        return getattr(import_module(self.home), f"run_{self.name}")


#: The stages, in run order.
REGISTRY: tuple[Stage, ...] = (
    Stage("pose2d", default_on=True, artifact="pose2d.h5", results_group=True),
    Stage(
        "bundle_adjustment",
        default_on=True,
        artifact="bundle_adjustment.h5",
        results_group=True,
        hint="check its 2D (are the views' points of one fly, in raw-frame pixels?) "
        "and the starting rig (cameras, calibration.file), or set "
        "pipeline.do_bundle_adjustment: false",
        memory=(380, 30),
    ),
    Stage(
        "pictorial_structures",
        default_on=False,
        artifact="pictorial_structures.h5",
        results_group=True,
        solves_3d=True,
        hint="check the detector's 2D and the rig, or set pipeline.do_pictorial_structures: false",
    ),
    Stage(
        "triangulation",
        default_on=True,
        artifact="triangulation.h5",
        results_group=True,
        solves_3d=True,
        hint="check its 2D (pose2d, corrections) and the rig (bundle adjustment's "
        "result, cameras, calibration.file)",
        memory=(110, 120),
    ),
    Stage(
        "refinement",
        default_on=True,
        needs_one_of=("triangulation",),
        artifact="refinement.h5",
        results_group=True,
        solves_3d=True,
        hint="check triangulation's 3D (flylib inspect) and the refinement settings, or "
        "set pipeline.do_refinement: false",
        memory=(410, 140),
    ),
    Stage("assemble", default_on=None, memory=(160, 130)),
    Stage(
        "kinematics",
        default_on=True,
        needs_one_of=("triangulation", "pictorial_structures"),
        hint="check the 3D in results.h5 (flylib inspect), or set pipeline.do_kinematics: false",
        memory=(130, 105),
    ),
    Stage("neuromechfly", default_on=False, needs_one_of=("triangulation", "pictorial_structures")),
    Stage("visualization", default_on=True),
)

#: The stages that solve a 3D pose (:attr:`Stage.solves_3d`), in run order.
SOLVES_3D: tuple[str, ...] = tuple(stage.name for stage in REGISTRY if stage.solves_3d)
#: Where a result's final 3D comes from: the first of these that ran (last in run order first).
FINAL_3D: tuple[str, ...] = SOLVES_3D[::-1]

_BY_NAME = {stage.name: stage for stage in REGISTRY}
#: ``stage -> its inputs class``, filled by :func:`register` as the stage homes import.
_INPUTS: dict[str, type] = {}


def by_name(name: str) -> Stage:
    """The record of stage ``name`` (ValueError for an unknown stage)."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown stage {name!r} (known: {', '.join(_BY_NAME)})") from None


def run_function(name: str) -> Any:
    """``run_<name>`` of stage ``name``'s home (:meth:`Stage.run_function`)."""
    return by_name(name).run_function()


T = TypeVar("T", bound=type)


def register(cls: T) -> T:
    """Class decorator: make ``cls`` the inputs class of stage ``cls.STAGE`` (ValueError for
    an unknown stage)."""
    by_name(cls.STAGE)  # type: ignore[attr-defined]
    _INPUTS[cls.STAGE] = cls  # type: ignore[attr-defined]
    return cls
