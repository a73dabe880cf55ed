"""What each stage reads: one frozen, typed inputs object per stage, built here.

An inputs object holds everything a stage's result depends on (params, rig, skeleton) plus, in
``runtime``, knobs that only change its speed. :meth:`StageInputs.params` is the *tracked*
part: the canonical JSON the rule carries as ``params.stage``, hashed into every artifact's
provenance, so Snakemake re-runs the job exactly when it changes. A job rebuilds its inputs
from that JSON (:meth:`StageInputs.from_params`) and the untracked ``params.runtime``: a stage
reads only what its rule tracks, by construction.

Each field is written and read back by its annotated type (:func:`_dump`, :func:`_load`); its
``dataclasses.field`` metadata may rename it (``key``) or track it only off its default
(``track_default=False``). Each stage's class lives in ``flylib.pipeline.<stage>``, registered
with :func:`register`; :func:`stage_inputs` builds one from a :class:`~flylib.config.Config`,
the only place below the workflow where a config object is read.
"""

from __future__ import annotations

import json
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

from ..config import Config
from ..config.canonical import canonical as _canonical
from ..config.checks import tracked_table
from ..config.params import TriangulationParams, build_params
from ..stages import by_name, register

__all__ = [
    "RigSpec",
    "SkeletonSpec",
    "StageInputs",
    "inputs_class",
    "register",
    "stage_inputs",
    "stage_params",
    "stage_runtime",
]


@dataclass(frozen=True)
class SkeletonSpec:
    """The skeleton table a stage reads: ``point_names`` in every array's points-axis order,
    ``limbs`` in table order; ``palette`` and ``name`` only for stages that draw or name it
    (``None`` elsewhere, so not in those stages' params)."""

    point_names: tuple[str, ...]
    limbs: tuple[tuple[str, tuple[str, ...]], ...]
    palette: Mapping[str, str] | None = None
    name: str | None = None

    @classmethod
    def from_config(cls, config: Config, *, palette: bool = False, name: bool = False):
        """The config's ``skeleton`` table (the default fly's when it has none)."""
        from ..skeleton import default_skeleton_table

        table = config.data.get("skeleton") or default_skeleton_table()
        return cls(
            point_names=tuple(table["point_names"]),
            limbs=tuple((k, tuple(v)) for k, v in (table.get("limb_points") or {}).items()),
            palette=dict(table.get("limb_palette") or {}) if palette else None,
            name=str(table.get("name", "skeleton")) if name else None,
        )

    @classmethod
    def from_params(cls, table: Mapping) -> SkeletonSpec:
        """Inverse of :meth:`params`."""
        return cls(
            point_names=tuple(table["point_names"]),
            limbs=tuple((k, tuple(v)) for k, v in table["limbs"]),
            palette=dict(table["palette"]) if "palette" in table else None,
            name=table.get("name"),
        )

    def params(self) -> dict:
        """``{"point_names": [...], "limbs": [[limb, [points]], ...]}`` (+ palette, name)."""
        out: dict[str, Any] = {
            "point_names": list(self.point_names),
            "limbs": [[k, list(v)] for k, v in self.limbs],
        }
        if self.palette is not None:
            out.update(palette=dict(self.palette), name=self.name)
        return out

    def skeleton(self):
        """The :class:`~flylib.skeleton.Skeleton` (palette and name where held)."""
        from ..skeleton import Skeleton

        table: dict[str, Any] = {
            "point_names": list(self.point_names),
            "limb_points": {k: list(v) for k, v in self.limbs},
        }
        if self.palette is not None:
            table["limb_palette"] = dict(self.palette)
        if self.name is not None:
            table["name"] = self.name
        return Skeleton.from_spec(table)


@dataclass(frozen=True)
class RigSpec:
    """The config rig a stage reads: the ``cameras`` table (``defaults`` included) and the
    ``calibration`` table (``None``: an orbit rig from ``cameras``), in the order of ``views``,
    the V axis of every points array. ``config_dir`` (where a relative calibration path is
    looked up after the recording's folder) is untracked: the file is itself a rule input."""

    views: tuple[str, ...]
    cameras: Mapping[str, Any]
    calibration: Mapping[str, Any] | None
    config_dir: Path | None = None

    @classmethod
    def from_config(cls, config: Config) -> RigSpec:
        calibration = config.data.get("calibration")
        if calibration and calibration.get("mirror") is False:
            # a knob added later: its default leaves the params (and their hash) as before
            calibration = {k: v for k, v in calibration.items() if k != "mirror"}
        return cls(
            views=tuple(config.view_names()),
            cameras=dict(config.data.get("cameras") or {}),
            calibration=dict(calibration) if calibration else None,
            config_dir=Path(config.source).parent if config.source else None,
        )

    @classmethod
    def from_params(cls, table: Mapping, config_dir: Path | str | None = None) -> RigSpec:
        """Inverse of :meth:`params`."""
        calibration = table.get("calibration")
        views = tuple(table["views"])
        # canonical params sort the cameras by name; the rig's camera order is the views'
        cameras = dict(table.get("cameras") or {})
        cameras = {
            **{v: cameras[v] for v in views if v in cameras},
            **{k: v for k, v in cameras.items() if k not in views},
        }
        return cls(
            views=views,
            cameras=cameras,
            calibration=dict(calibration) if calibration else None,
            config_dir=Path(config_dir) if config_dir else None,
        )

    def params(self) -> dict:
        """``{"views", "cameras", "calibration"}``: the rig as the params hold it."""
        return {
            "views": list(self.views),
            "cameras": dict(self.cameras),
            "calibration": dict(self.calibration) if self.calibration else None,
        }

    def camera_group(
        self,
        image_sizes: Mapping[str, tuple[int, int]] | None = None,
        recording_dir: str | Path | None = None,
    ):
        """The :class:`~flylib.camera.rig.CameraGroup`, one camera per view in order: the
        calibration file's when set, else the orbit rig of ``cameras`` (principal points from
        ``image_sizes``)."""
        if self.calibration:
            from ..interop.anipose import load_calibration

            return load_calibration(
                dict(self.calibration),
                self.views,
                Path(recording_dir) if recording_dir else None,
                image_sizes=image_sizes,
                config_dir=self.config_dir,
            )
        from ..camera.rig import CameraGroup

        cameras = dict(self.cameras)
        defaults = cameras.pop("defaults", {}) or {}
        # the tracked params hold the table with sorted keys: the views give the order back
        specs = {view: cameras[view] for view in self.views if view in cameras}
        specs.update({name: spec for name, spec in cameras.items() if name not in specs})
        return CameraGroup.from_table(specs, defaults, dict(image_sizes or {}))


def _dump(value: Any) -> Any:
    """A field's value as the tracked params hold it."""
    if isinstance(value, (RigSpec, SkeletonSpec)):
        return value.params()
    if isinstance(value, TriangulationParams):  # only the knobs the method reads
        return value.method_params()
    if is_dataclass(value):  # a typed params class of flylib.config
        return tracked_table(value)
    return value


def _load(hint: Any, value: Any, runtime: Any) -> Any:
    """Inverse of :func:`_dump` for a field annotated ``hint``; a rig's calibration is
    looked up in the runtime's ``config_dir``."""
    if value is None:
        return None
    if typing.get_origin(hint) in (typing.Union, types.UnionType):  # X | None
        (hint,) = (arg for arg in typing.get_args(hint) if arg is not type(None))
    if hint is RigSpec:
        return RigSpec.from_params(value, getattr(runtime, "config_dir", None))
    if hint is SkeletonSpec:
        return SkeletonSpec.from_params(value)
    if is_dataclass(hint):
        from_table = getattr(hint, "from_table", None)
        return from_table(value) if from_table else build_params(hint, value)
    return tuple(value) if typing.get_origin(hint) is tuple else value


@dataclass(frozen=True)
class StageInputs:
    """Base of the per-stage inputs objects (frozen dataclasses). Subclasses set
    :attr:`STAGE`, define :meth:`from_config`, and keep speed-only knobs in a ``runtime``
    field, the one field :meth:`params` leaves out; every other is tracked under its
    metadata's ``key`` (default: its name), a ``track_default: False`` one only off its default
    (so params made before it existed stay equal)."""

    STAGE = ""  # a class attribute, not a dataclass field (no annotation)

    @classmethod
    def from_config(cls, config: Config) -> StageInputs:
        raise NotImplementedError(cls.__name__)

    @classmethod
    def _tracked_fields(cls):
        return [f for f in fields(cls) if f.name != "runtime"]

    @classmethod
    def from_params(cls, params: Mapping, runtime: Any = None) -> StageInputs:
        """Rebuild the inputs from :meth:`params` (the rule's ``params.stage``, parsed) and
        the untracked ``runtime`` (``None``: the class's default runtime)."""
        kwargs = {}
        own = {f.name: f for f in fields(cls)}
        if "runtime" in own:
            kwargs["runtime"] = runtime = own["runtime"].default if runtime is None else runtime
        hints = typing.get_type_hints(cls)
        for f in cls._tracked_fields():
            key = f.metadata.get("key", f.name)
            if key in params:  # absent: a track_default=False field at its default
                kwargs[f.name] = _load(hints[f.name], params[key], runtime)
        return cls(**kwargs)

    def params(self) -> dict:
        """The tracked params: every field but ``runtime``, as :func:`_dump` writes it."""
        out = {}
        for f in self._tracked_fields():
            value = getattr(self, f.name)
            if f.metadata.get("track_default", True) or value != f.default:
                out[f.metadata.get("key", f.name)] = _dump(value)
        return out

    @property
    def runtime_options(self) -> Any:
        """The untracked part (``runtime`` field, ``None`` when the stage has none)."""
        return getattr(self, "runtime", None)

    def canonical_params(self) -> dict:
        """:meth:`params` canonicalised and checked to be JSON."""
        canonical = _canonical(self.params())
        json.dumps(canonical)  # fail here, not in the workflow, if something is not JSON-able
        return canonical


def inputs_class(stage: str) -> type[StageInputs]:
    """``stage``'s inputs class, importing its home on first use (ValueError: unknown stage)."""
    return by_name(stage).inputs_class()


def stage_inputs(config: Config, stage: str) -> StageInputs:
    """``stage``'s inputs object as ``config`` gives them (ValueError: unknown stage)."""
    return inputs_class(stage).from_config(config)


def stage_params(config: Config, stage: str) -> dict:
    """The params ``stage``'s rule tracks under ``config`` (canonical JSON)."""
    return stage_inputs(config, stage).canonical_params()


def stage_runtime(config: Config, stage: str) -> Any:
    """The untracked runtime part of ``stage``'s inputs under ``config``."""
    return inputs_class(stage).from_config(config).runtime_options
