"""The embedded demo recording, built from a config: what the workflow's ``demo`` rule and
the tests run (:func:`flylib.demo.write_demo` with the config's settings, rig and skeleton)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config.sources import source_patterns, view_names, view_sources
from ..errors import ConfigError
from ..recordings.listing import TRUTH_FILE, dlc_filename
from .assemble import AssembleInputs
from .inputs import RigSpec, SkeletonSpec, StageInputs


@dataclass(frozen=True)
class DemoLayout:
    """The demo directory's files, as the config names them (untracked): ``view_sources``
    ``(view, source)``, the source feeding each view (the first ``pose2d.pathways`` source
    among its output points, else by name or position); ``source_files`` ``(source, file)``,
    one ``.mp4`` per source; ``dlc_files``, one DeepLabCut CSV name per view, in view order."""

    view_sources: tuple[tuple[str, str], ...] = ()
    source_files: tuple[tuple[str, str], ...] = ()
    dlc_files: tuple[str, ...] = ()

    @classmethod
    def from_config(cls, config) -> DemoLayout:
        """The layout ``config`` gives; ConfigError if a source's file is not ``<name>.mp4``."""
        dlc = demo_files(config)["dlc"]
        return cls(
            view_sources=tuple(view_sources(config).items()),
            source_files=tuple(source_patterns(config).items()),
            dlc_files=tuple(dlc),
        )


@dataclass(frozen=True)
class DemoInputs(StageInputs):
    """The demo's inputs: ``settings`` (the ``demo`` table over the defaults), ``sources``,
    the config ``rig`` (its cameras' orbit; a calibration file is not read), the whole
    ``skeleton`` (drawn) and ``output_points`` (``pose2d.output_points``: what each view sees)."""

    STAGE = "demo"

    settings: Mapping[str, Any] = field(metadata={"key": "demo"})
    sources: Any
    rig: RigSpec
    skeleton: SkeletonSpec
    output_points: Mapping[str, Any] | None
    runtime: DemoLayout = DemoLayout()

    @classmethod
    def from_config(cls, config) -> DemoInputs:
        """The demo as ``config`` describes it; ConfigError for an invalid ``demo`` table or
        file layout, or a config without a ``skeleton`` table."""
        from ..demo import demo_settings

        if "skeleton" not in config.data:
            raise ConfigError(
                f"{config.source or 'config'}: no 'skeleton' table; add one or use Skeleton.fly()"
            )
        assemble = AssembleInputs.from_config(config)
        output_points = (config.data.get("pose2d") or {}).get("output_points")
        return cls(
            settings=demo_settings(config.data.get("demo")),
            sources=config.data.get("sources"),
            rig=assemble.rig,
            skeleton=assemble.skeleton,
            output_points=output_points,
            runtime=DemoLayout.from_config(config),
        )

    def rule_params(self) -> str:
        """The demo rule's tracked ``params.stage``: :meth:`params` as sorted JSON."""
        return json.dumps(self.params(), sort_keys=True)


def _orbit_rig(rig: RigSpec, image_size: tuple[int, int]):
    """The orbit rig of ``rig``'s ``cameras``, principal points at ``image_size``'s centre."""
    from dataclasses import replace

    return replace(rig, calibration=None).camera_group({v: image_size for v in rig.views})


def run_demo(inputs: DemoInputs, directory: str | Path, **overrides: Any):
    """Generate the demo recording into ``directory`` (created if needed), ``overrides`` over
    ``inputs.settings`` (e.g. ``frames=10``); returns the :class:`flylib.demo.DemoRecording`."""
    from ..demo import demo_settings, view_visibility, write_demo

    settings = demo_settings({**inputs.settings, **overrides})
    skeleton = inputs.skeleton.skeleton()
    cameras = _orbit_rig(inputs.rig, (settings["height"], settings["width"]))
    layout = inputs.runtime
    return write_demo(
        directory,
        settings,
        skeleton,
        cameras,
        view_visibility(inputs.output_points, list(cameras.names), skeleton.point_names),
        dict(layout.view_sources),
        dict(layout.source_files),
        layout.dlc_files,
    )


def make_demo(config, directory: str | Path, **overrides: Any):
    """Write the demo recording ``config`` describes into ``directory``, ``overrides`` over its
    ``demo`` table (e.g. ``frames=10``)."""
    return run_demo(DemoInputs.from_config(config), directory, **overrides)


def demo_files(config: Any) -> dict[str, list[str]]:
    """File names :func:`make_demo` writes, relative to the demo directory: ``footage`` (one
    video per source), ``dlc`` (one CSV per view, in view order) and ``truth``."""
    patterns = source_patterns(config)
    for name, pattern in patterns.items():
        if any(c in pattern for c in "*?[") or Path(pattern).suffix.lower() != ".mp4":
            raise ConfigError(
                f"sources: {name!r} has filename {pattern!r}; the demo writes one "
                ".mp4 per source, so each source needs a plain '<name>.mp4' filename"
            )
    by_view, views = view_sources(config), view_names(config)
    if missing := [v for v in views if v not in by_view]:
        raise ConfigError(
            f"cameras: {', '.join(missing)}: no footage source feeds it (the demo films one video "
            f"per source); add e.g. {{name: vid_{missing[0]}, filename: camera_{len(patterns)}.mp4}} "
            "to sources (a list is replaced whole: give every entry), or remove the camera (null)"
        )
    return {
        "footage": list(patterns.values()),
        "dlc": [dlc_filename(patterns[by_view[v]]) for v in views],
        "truth": [TRUTH_FILE],
    }


def demo_import_spec(config: Any) -> dict[str, Any]:
    """The ``pose2d.import`` entry reading the demo's CSVs (``files``: view -> relative CSV)."""
    return {"format": "dlc_csv", "files": dict(zip(view_names(config), demo_files(config)["dlc"]))}
