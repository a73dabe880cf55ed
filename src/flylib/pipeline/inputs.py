"""What each stage reads: one frozen, typed inputs object per stage, built here.

A stage's inputs object holds everything its result depends on (its params, the rig
and skeleton it needs) plus, in ``runtime``, the knobs that only change how fast it
runs. :meth:`StageInputs.params` is the stage's *tracked* params: the canonical JSON
its workflow rule carries as ``params.stage``, hashed into every artifact's
provenance, so Snakemake re-runs the job exactly when it changes. A job rebuilds its
inputs object from that JSON (:meth:`StageInputs.from_params`) and the rule's
untracked ``params.runtime``; a stage therefore reads only what its rule tracks, by
construction.

Each stage's class lives in the stage's home (``flylib.pipeline.<stage>``) and is
registered with :func:`register` (:func:`flylib.stages.register`, re-exported here for
the homes); :func:`stage_inputs` builds any stage's inputs
from a :class:`~flylib.config.Config`, which is the only place below the workflow
where a config object is read.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

from ..config import Config
from ..config.canonical import canonical as _canonical
from ..config.checks import tracked_table
from ..config.params import TriangulationParams, build_params
from ..stages import by_name, register

__all__ = [
    "DATA",
    "FULL_SKELETON",
    "OPTIONAL_RIG",
    "RIG",
    "SKELETON",
    "TRIANGULATION",
    "Codec",
    "RigSpec",
    "SkeletonSpec",
    "StageInputs",
    "frozen_mapping",
    "register",
    "stage_inputs",
    "stage_params",
    "stage_runtime",
    "tracked",
    "typed_params",
    "plain_json",
]


class FrozenDict(dict):
    """A dict that refuses changes (an inputs object's nested tables), hashable by
    its canonical JSON."""

    def _refuse(self, *args, **kwargs):
        raise TypeError("a stage's inputs are read-only")

    __setitem__ = __delitem__ = clear = pop = popitem = setdefault = update = _refuse

    def __hash__(self) -> int:  # type: ignore[override]
        return hash(json.dumps(_canonical(self), sort_keys=True))

    def __deepcopy__(self, memo) -> dict:
        return {k: copy.deepcopy(v, memo) for k, v in self.items()}

    def __reduce__(self):
        return (FrozenDict, (dict(self),))


def frozen_mapping(value: Any) -> Any:
    """``value`` with every mapping made a :class:`FrozenDict` and every list a tuple
    (a deep, read-only copy)."""
    if isinstance(value, Mapping):
        return FrozenDict({k: frozen_mapping(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(frozen_mapping(v) for v in value)
    return value


def plain_json(value: Any) -> Any:
    """A plain JSON copy of a frozen value (tuples back to lists, FrozenDicts to dicts)."""
    if isinstance(value, Mapping):
        return {k: plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(v) for v in value]
    return value


@dataclass(frozen=True)
class SkeletonSpec:
    """The skeleton table a stage reads: ``point_names`` in the order of every array's
    points axis, ``limbs`` in table order. ``palette`` and ``name`` are only for the
    stages that draw or name it (``None`` elsewhere, so they are not in those stages'
    params)."""

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
            palette=frozen_mapping(dict(table.get("limb_palette") or {})) if palette else None,
            name=str(table.get("name", "skeleton")) if name else None,
        )

    @classmethod
    def from_params(cls, structure: Mapping, *, palette=None, name=None) -> SkeletonSpec:
        """Inverse of :meth:`structure` (plus the palette and name where tracked)."""
        return cls(
            point_names=tuple(structure["point_names"]),
            limbs=tuple((k, tuple(v)) for k, v in structure["limbs"]),
            palette=frozen_mapping(dict(palette)) if palette is not None else None,
            name=name,
        )

    def structure(self) -> dict:
        """``{"point_names": [...], "limbs": [[limb, [points]], ...]}``: the part of
        the skeleton every geometry stage's params hold."""
        return {
            "point_names": list(self.point_names),
            "limbs": [[k, list(v)] for k, v in self.limbs],
        }

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
    """The config rig a stage reads: the ``cameras`` table (``defaults`` included) and
    the ``calibration`` table (``None``: an orbit rig from ``cameras``), in the order of
    ``views``, the V axis of every points array. ``config_dir`` (the config file's
    folder) is where a relative calibration path is looked up after the recording's
    folder; not tracked: the calibration file itself is an input of the rules that read
    it.
    """

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
            cameras=frozen_mapping(dict(config.data.get("cameras") or {})),
            calibration=frozen_mapping(dict(calibration)) if calibration else None,
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
            cameras=frozen_mapping(cameras),
            calibration=frozen_mapping(dict(calibration)) if calibration else None,
            config_dir=Path(config_dir) if config_dir else None,
        )

    def params(self) -> dict:
        """``{"views", "cameras", "calibration"}``: the rig as the params hold it."""
        return {
            "views": list(self.views),
            "cameras": plain_json(self.cameras),
            "calibration": plain_json(self.calibration) if self.calibration else None,
        }

    def camera_group(
        self,
        image_sizes: Mapping[str, tuple[int, int]] | None = None,
        recording_dir: str | Path | None = None,
    ):
        """The :class:`~flylib.camera.rig.CameraGroup`: the calibration file's when set
        (:func:`flylib.interop.anipose.load_calibration`), else the orbit rig of
        ``cameras`` (:meth:`~flylib.camera.rig.CameraGroup.from_table`, principal points
        from ``image_sizes``), one camera per view in :attr:`views` order."""
        if self.calibration:
            from ..interop.anipose import load_calibration

            return load_calibration(
                plain_json(self.calibration),
                self.views,
                Path(recording_dir) if recording_dir else None,
                image_sizes=image_sizes,
                config_dir=self.config_dir,
            )
        from ..camera.rig import CameraGroup

        cameras = plain_json(self.cameras)
        defaults = cameras.pop("defaults", {}) or {}
        # the tracked params hold the table with sorted keys: the views give the order back
        specs = {view: cameras[view] for view in self.views if view in cameras}
        specs.update({name: spec for name, spec in cameras.items() if name not in specs})
        return CameraGroup.from_table(specs, defaults, dict(image_sizes or {}))


@dataclass(frozen=True)
class Codec:
    """How one field of an inputs object is written into the tracked params and read
    back: ``load(dump(value), runtime) == value``, ``runtime`` being the inputs'
    untracked part (e.g. where a calibration is found)."""

    dump: Callable[[Any], Any]
    load: Callable[[Any, Any], Any]


def _config_dir(runtime: Any) -> Path | None:
    return getattr(runtime, "config_dir", None)


#: Plain data (strings, names, tables): JSON out, read-only back (FrozenDicts, tuples).
DATA = Codec(plain_json, lambda value, runtime: frozen_mapping(value))
#: A :class:`SkeletonSpec` as its points and limbs (:meth:`SkeletonSpec.structure`).
SKELETON = Codec(
    lambda skeleton: skeleton.structure(), lambda table, runtime: SkeletonSpec.from_params(table)
)
#: A :class:`SkeletonSpec` with its palette and name (the stages that draw or name it).
FULL_SKELETON = Codec(
    lambda skeleton: {
        **skeleton.structure(),
        "palette": dict(skeleton.palette or {}),
        "name": skeleton.name,
    },
    lambda table, runtime: SkeletonSpec.from_params(
        table, palette=table["palette"], name=table["name"]
    ),
)
#: A :class:`RigSpec` (:meth:`RigSpec.params`), its calibration looked up in the
#: runtime's ``config_dir``.
RIG = Codec(
    lambda rig: rig.params(),
    lambda table, runtime: RigSpec.from_params(table, _config_dir(runtime)),
)
#: A :class:`RigSpec`, or ``None`` while bundle adjustment is on (the rig is then in that
#: stage's artifact).
OPTIONAL_RIG = Codec(
    lambda rig: rig.params() if rig is not None else None,
    lambda table, runtime: RigSpec.from_params(table, _config_dir(runtime)) if table else None,
)


def typed_params(cls: type, dump: Callable[[Any], Any] = tracked_table) -> Codec:
    """A typed params dataclass of :mod:`flylib.config` (``cls``) as its table: every
    field (:func:`~flylib.config.checks.tracked_table`), or what ``dump`` gives."""
    return Codec(dump, lambda table, runtime: build_params(cls, table))


#: The triangulation method and the knobs it reads
#: (:meth:`~flylib.config.params.TriangulationParams.method_params`).
TRIANGULATION = typed_params(TriangulationParams, dump=TriangulationParams.method_params)


def tracked(
    codec: Codec = DATA, *, key: str | None = None, track_default: bool = True, **kwargs
) -> Any:
    """A tracked field of an inputs class: held in :meth:`StageInputs.params` under
    ``key`` (default: the field's name) as ``codec`` writes it. ``track_default=False``
    (with a ``default``): only when not at that default, so the params made before the
    field existed stay equal. ``kwargs`` go to :func:`dataclasses.field`."""
    return field(metadata={"codec": codec, "key": key, "track_default": track_default}, **kwargs)


@dataclass(frozen=True)
class StageInputs:
    """Base of the per-stage inputs objects (frozen dataclasses).

    Subclasses set :attr:`STAGE`, define :meth:`from_config`, and keep their speed-only
    knobs in a ``runtime`` field (absent for a stage that has none), the one field
    :meth:`params` leaves out. Every other field is tracked: :meth:`params` and its
    inverse :meth:`from_params` are made from the fields, each written as its
    :func:`tracked` metadata says (:data:`DATA` when it has none).
    """

    STAGE = ""  # a class attribute, not a dataclass field (no annotation)

    @classmethod
    def from_config(cls, config: Config) -> StageInputs:
        raise NotImplementedError(cls.__name__)

    @classmethod
    def _tracked_fields(cls):
        return [f for f in fields(cls) if f.name != "runtime"]

    @classmethod
    def from_params(cls, params: Mapping, runtime: Any = None) -> StageInputs:
        """Rebuild the inputs from :meth:`params` (the rule's ``params.stage``) and the
        untracked ``runtime`` (``None``: the class's default runtime)."""
        kwargs = {}
        own = {f.name: f for f in fields(cls)}
        if "runtime" in own:
            kwargs["runtime"] = runtime = own["runtime"].default if runtime is None else runtime
        for f in cls._tracked_fields():
            key = f.metadata.get("key") or f.name
            if key in params or f.default is MISSING:  # absent: untracked at its default
                kwargs[f.name] = f.metadata.get("codec", DATA).load(params[key], runtime)
        return cls(**kwargs)

    def params(self) -> dict:
        """The tracked params: every field but ``runtime``, as its codec writes it."""
        out = {}
        for f in self._tracked_fields():
            value = getattr(self, f.name)
            if f.metadata.get("track_default", True) or value != f.default:
                key = f.metadata.get("key") or f.name
                out[key] = f.metadata.get("codec", DATA).dump(value)
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
    """The inputs class of ``stage``, importing its home on first use (ValueError for
    an unknown stage)."""
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


def inputs_from_job(stage: str, params_json: str | Mapping, runtime: Any) -> StageInputs:
    """A Snakemake job's inputs: rebuilt from the rule's tracked ``params.stage`` (JSON
    text) and its untracked ``params.runtime``."""
    params = json.loads(params_json) if isinstance(params_json, str) else params_json
    return inputs_class(stage).from_params(params, runtime)
