"""The config a stage may read: exactly what its workflow rule tracks.

Each rule tracks ``params: stage=<Config.stage_params(stage)>``, so Snakemake re-runs a
job when, and only when, that subset changes. A stage function therefore runs on a
:class:`StageConfig`: the run's config cut down to the paths :func:`stage_reads`
declares for the stage, where reading any other key raises
:class:`UntrackedConfigRead` instead of returning the user's value. That the
declared paths are tracked (a change to any of them changes the stage's params) is
what ``tests/test_tracked.py`` checks, key by key.

A declared path is one of

- ``"a.b"``: the value at ``a.b`` and everything below it;
- ``"a.b:names"``: only the keys of the mapping at ``a.b`` (the camera names of a rig
  whose geometry the stage does not use).

Some reads are not in the stage's own params by design, each listed with why:
:data:`UNTRACKED` (speed-only knobs, names carried by the output file's name) and
:func:`upstream_reads` (inputs fixed by an upstream stage whose artifact this stage
reads, so a change re-runs that stage and, through its artifact, this one).
"""

from __future__ import annotations

import copy
from collections.abc import Iterator, Mapping
from typing import Any

from ..config import Config

#: Marks a mapping whose keys may be listed but whose values may not be read.
_NAMES = "names"

#: Reads that never change a stage's result, or that its output's name carries:
#: ``stage -> {path: why}``.
UNTRACKED: dict[str, dict[str, str]] = {
    "pose2d": {
        "pose2d.batch_size": "speed only",
        "pose2d.decode_buffer": "speed only",
        "pose2d.device": "where the detector runs (speed only)",
        "pose2d.compile": "torch.compile or not (speed only)",
        "io.image.workers": "speed only",
        "pictorial_structures.k": "named in the candidates file (stages/candidates_k<k>.h5)",
    },
    "bundle_adjustment": {
        "bundle_adjustment.verbose": "logging only",
        "bundle_adjustment.workers": "speed only",
    },
}

_SKELETON = ("skeleton.point_names", "skeleton.limb_points")


def stage_reads(config: Config, stage: str) -> tuple[str, ...]:
    """The config paths ``stage`` may read under ``config`` (see the module doc).

    Parameters
    ----------
    config
        The run's full config (which stages are on decides where the rig comes from).
    stage
        A :data:`flylib.config.PARAM_STAGES` name.

    Returns
    -------
    tuple of str
        The declared paths.
    """
    flags = config.stage_flags()
    rig = ("cameras", "calibration")
    if not config.camera_table()[1]:  # the views are named by pose2d.output_points
        rig += ("pose2d.output_points:names",)
    own_rig = () if flags["bundle_adjustment"] else rig
    if stage == "pose2d":
        return (
            "sources",
            "pose2d",
            "skeleton.point_names",
            "cameras:names",
            "io.on_corrupt_frame",
            *UNTRACKED["pose2d"],
        )
    if stage == "bundle_adjustment":
        return ("bundle_adjustment", *rig, *_SKELETON)
    if stage == "pictorial_structures":
        return ("pictorial_structures", *_SKELETON, *own_rig)
    method = tuple(f"triangulation.{key}" for key in config.triangulation.method_params())
    if stage == "triangulation":  # the skeleton: its accuracy's bone figures
        return (*method, *_SKELETON, *own_rig)
    if stage == "refinement":  # its held-out-view check re-runs the triangulation
        return ("refinement", *method, *_SKELETON, *own_rig)
    if stage == "kinematics":
        return ("kinematics", *_SKELETON)
    if stage == "neuromechfly":
        return ("neuromechfly", *_SKELETON)
    if stage == "assemble":
        return (
            *rig,
            "skeleton.point_names",
            "skeleton.limb_points",
            "skeleton.limb_palette",
            "skeleton.name",
        )
    if stage == "visualization":
        return ("visualization", "skeleton.limb_palette", *upstream_reads(stage))
    raise ValueError(f"unknown stage {stage!r}")


def upstream_reads(stage: str) -> dict[str, str]:
    """Paths ``stage`` reads that an upstream stage's params track: ``path -> stage``.

    Visualization finds each view's footage as pose2d did (``sources``, the views'
    pathways): a change there re-runs pose2d, and so everything after it.
    """
    if stage == "visualization":
        return {
            "sources": "pose2d",
            "pose2d.pathways": "pose2d",
            "pose2d.output_points": "pose2d",
            "cameras:names": "pose2d",
            "io.on_corrupt_frame": "pose2d",
        }
    return {}


class UntrackedConfigRead(RuntimeError):
    """A stage read a config key its rule does not track (a bug in flylib, not in the
    user's config: the stage's result would not be redone when that key changes)."""


def _tree(paths) -> dict:
    """``"a.b"`` paths as a nested dict: ``True`` for a whole subtree, ``_NAMES`` for
    keys only."""
    tree: dict = {}
    for path in paths:
        path, _, mode = path.partition(":")
        *parents, last = path.split(".")
        node = tree
        for key in parents:
            child = node.setdefault(key, {})
            if child is True:
                break
            node = child
        else:
            if node.get(last) is not True:
                node[last] = _NAMES if mode == _NAMES else True
    return tree


class _Tracked(Mapping):
    """A read-only view of a config mapping that lets through only the declared keys."""

    def __init__(self, data: Mapping, tree: dict, stage: str, prefix: str = "") -> None:
        self._data, self._tree, self._stage, self._prefix = data, tree, stage, prefix

    def _refuse(self, key) -> UntrackedConfigRead:
        return UntrackedConfigRead(
            f"stage {self._stage!r} read config key {self._prefix}{key!r}, which its rule "
            "does not track (flylib.pipeline.tracked.stage_reads)"
        )

    def __getitem__(self, key):
        if key not in self._tree:
            raise self._refuse(key)
        value, node = self._data[key], self._tree[key]
        if node is True:
            return copy.deepcopy(value)
        if not isinstance(value, Mapping):
            return value
        if node == _NAMES:
            return _Names(value, f"{self._prefix}{key}.", self._stage)
        return _Tracked(value, node, self._stage, f"{self._prefix}{key}.")

    def get(self, key, default=None):
        if key not in self._tree:
            raise self._refuse(key)
        return self[key] if key in self._data else default

    def __contains__(self, key) -> bool:
        # An untracked key looks absent, so a typed view gives its default, never the user's value.
        return key in self._tree and key in self._data

    def __iter__(self) -> Iterator:
        return (key for key in self._data if key in self._tree)

    def __len__(self) -> int:
        return sum(1 for _ in self)


class _Names(Mapping):
    """A mapping whose keys may be listed but whose values are not tracked."""

    def __init__(self, data: Mapping, prefix: str, stage: str) -> None:
        self._data, self._prefix, self._stage = data, prefix, stage

    def __getitem__(self, key):
        raise UntrackedConfigRead(
            f"stage {self._stage!r} read config key {self._prefix}{key!r}, of which its rule "
            "tracks only the names (flylib.pipeline.tracked.stage_reads)"
        )

    def __contains__(self, key) -> bool:
        return key in self._data

    def __iter__(self) -> Iterator:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)


def _plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _plain(value[k]) for k in value}
    return value


class StageConfig(Config):
    """A :class:`~flylib.config.Config` that holds only what one stage may read.

    Build one with :meth:`for_stage`. Its typed views (``.triangulation``,
    ``.bundle_adjustment``, ...) and :meth:`skeleton` see only the declared keys (the
    rest take their defaults or, when read directly, raise
    :class:`UntrackedConfigRead`); :meth:`stage_params` returns the stage's params as
    computed from the full config, for the artifact's provenance.

    Attributes
    ----------
    stage
        The stage.
    params
        ``Config.stage_params(stage)`` of the full config: what the rule tracks.
    """

    def __init__(self, config: Config, stage: str) -> None:
        # Not Config.__init__: the full config was validated; this is a view of it.
        self.stage = stage
        self.params = config.stage_params(stage)
        self.data = _Tracked(config.data, _tree(stage_reads(config, stage)), stage)  # type: ignore[assignment]
        self.text = None
        self.source = config.source
        self.format = "yaml"

    def __repr__(self) -> str:
        return f"StageConfig({self.stage!r}, source={str(self.source) if self.source else None!r})"

    @classmethod
    def for_stage(cls, config: Config, stage: str) -> StageConfig:
        """``config`` cut down to what ``stage`` may read (itself if it already is).

        Raises
        ------
        UntrackedConfigRead
            If ``config`` is already cut down for another stage.
        """
        if isinstance(config, StageConfig):
            if config.stage != stage:
                raise UntrackedConfigRead(
                    f"stage {stage!r} was given the config of stage {config.stage!r}"
                )
            return config
        return cls(config, stage)

    def tracks(self, key: str) -> bool:
        """Whether this stage may read the top-level config ``key``."""
        return key in self.data._tree

    def stage_params(self, stage: str) -> dict:
        """The stage's params, as the full config gives them (only for this stage)."""
        if stage != self.stage:
            raise UntrackedConfigRead(
                f"stage {self.stage!r} asked for the params of stage {stage!r}"
            )
        return copy.deepcopy(self.params)

    def skeleton(self):
        """The skeleton, with only the parts of the ``skeleton`` table this stage tracks
        (the default fly skeleton's, where the config has no table)."""
        from ..skeleton import Skeleton, default_skeleton_table

        table = self.data.get("skeleton")
        if not table:
            node = self.data._tree.get("skeleton", {})
            default = default_skeleton_table()
            table = default if node is True else {k: default[k] for k in node if k in default}
        return Skeleton.from_spec(_plain(table))

    def snapshot_text(self) -> str:
        raise UntrackedConfigRead(f"stage {self.stage!r} asked for the whole config's text")
