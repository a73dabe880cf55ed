"""Which footage source feeds which view: pure functions of a :class:`~flylib.config.Config` or
its mapping, reading nothing from disk, so the recording resolver (:mod:`flylib.recordings`), the
2D import and the demo share them without importing one another."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..errors import ConfigError, ImportFormatError


def config_data(config: Any) -> dict:
    """The raw config mapping of a :class:`~flylib.config.Config` (or a plain dict)."""
    return config if isinstance(config, dict) else config.data


def view_names(config, *, required: bool = True) -> list[str]:
    """The configured views in config order: ``cameras`` entries except ``defaults``, else (a rig
    from a calibration file) the ``pose2d.output_points`` keys. An ImportFormatError when
    ``required`` and the config names no views at all."""
    data = config_data(config)
    names = [name for name in (data.get("cameras") or {}) if name != "defaults"]
    if not names:
        names = list((data.get("pose2d") or {}).get("output_points") or {})
    if required and not names:
        raise ImportFormatError(
            "config names no views (no cameras entries, no pose2d.output_points); define the rig's views"
        )
    return names


def view_sources(config) -> dict[str, str]:
    """:func:`feeding_sources` of the config's views, ``sources`` and ``pose2d`` tables."""
    data = config_data(config)
    return feeding_sources(view_names(config), data.get("sources") or [], data.get("pose2d") or {})


def feeding_sources(views, sources, pose2d) -> dict[str, str]:
    """Map each view to the footage source that feeds it: the first pathway listed for the view in
    ``pose2d.output_points``, else a source named ``vid_<view>`` or ``<view>``, else the source
    at the same position in ``sources`` (the ``{name, filename?}`` list)."""
    pathway_source = {
        p.get("name"): p.get("source")
        for p in pose2d.get("pathways") or []
        if isinstance(p, Mapping)
    }
    source_names = [s.get("name") for s in sources or [] if isinstance(s, Mapping)]
    out: dict[str, str] = {}
    for i, view in enumerate(views):
        points = (pose2d.get("output_points") or {}).get(view) or {}
        source = next(
            (
                pathway_source[entry["pathway"]]
                for entry in points.values()
                if isinstance(entry, Mapping) and pathway_source.get(entry.get("pathway"))
            ),
            None,
        )
        if source is None:
            source = next((c for c in (f"vid_{view}", view) if c in source_names), None)
        if source is None and i < len(source_names):
            source = source_names[i]
        if source is not None:
            out[view] = source
    return out


def source_patterns(config: Any) -> dict[str, str]:
    """Source name -> footage glob (``filename``, else the name), in config order, of a
    :class:`~flylib.config.Config` or a mapping."""
    return patterns_of(getattr(config, "data", config).get("sources") or [])


def patterns_of(sources) -> dict[str, str]:
    """Source name -> footage glob of a ``sources`` list (:func:`source_patterns`); an
    empty list or an entry without a string ``name`` is a ConfigError."""
    out: dict[str, str] = {}
    for i, entry in enumerate(sources or []):
        name = entry.get("name") if isinstance(entry, Mapping) else None
        if not isinstance(name, str) or not name:
            raise ConfigError(f"sources[{i}]: needs a string 'name' (got {entry!r})")
        out[name] = str(entry.get("filename", name))
    if not out:
        raise ConfigError(
            "sources: the config lists no footage sources; add a sources: list to the YAML config "
            "(entries such as {name: vid_rh, filename: camera_0.mp4}, as in config/config.yaml)"
        )
    return out


def footage_globs(config: Any) -> dict[str, str | None]:
    """``view -> footage glob`` of the source feeding each view (``None``: a source without a
    pattern), in view order: what :func:`flylib.interop.views.footage_files` matches."""
    sources = view_sources(config)
    patterns = source_patterns(config) if sources else {}
    return {view: patterns.get(source) for view, source in sources.items()}


def pathways_of(tables) -> set:
    """The detector pathways the ``output_points`` tables name."""
    return {
        slot.get("pathway")
        for table in tables
        if isinstance(table, Mapping)
        for slot in table.values()
        if isinstance(slot, Mapping)
    }


def drop_views(data: dict, views: set[str]) -> None:
    """Remove what only ``views`` used from a merged config mapping, in place: their
    ``pose2d.output_points``, the pathways only they read, the sources only those pathways (or
    the views by name) read, and the ``visualization`` panels showing them."""
    if not views:
        return
    pose2d = data.get("pose2d") if isinstance(data.get("pose2d"), dict) else {}
    points = pose2d.get("output_points") if isinstance(pose2d.get("output_points"), dict) else {}
    kept_points = {v: t for v, t in points.items() if v not in views}
    gone = pathways_of(t for v, t in points.items() if v in views) - pathways_of(
        kept_points.values()
    )
    if points:
        pose2d["output_points"] = kept_points
    pathways = pose2d.get("pathways")
    if isinstance(pathways, list):
        pose2d["pathways"] = [p for p in pathways if not _named(p, gone)]
        read = {p.get("source") for p in pathways if _named(p, gone)}
        read |= {n for v in views for n in (f"vid_{v}", v)}
        read -= {p.get("source") for p in pose2d["pathways"] if isinstance(p, Mapping)}
        if isinstance(data.get("sources"), list):
            data["sources"] = [s for s in data["sources"] if not _named(s, read)]
    videos = (data.get("visualization") or {}).get("videos")
    if isinstance(videos, list):
        kept = []
        for video in videos:
            panels = video.get("panels") if isinstance(video, Mapping) else None
            if isinstance(panels, list):
                left = [
                    p for p in panels if not (isinstance(p, Mapping) and p.get("view") in views)
                ]
                if not left:
                    continue
                video = {**video, "panels": left}
            kept.append(video)
        data["visualization"] = {**data["visualization"], "videos": kept}


def _named(entry: Any, names: set) -> bool:
    return isinstance(entry, Mapping) and entry.get("name") in names
