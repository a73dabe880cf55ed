"""Video and panel specs: parsing and validating ``[visualization]``, merging draw kwargs.

A video is an ordered list of panels drawn onto one canvas, each a ``plot`` of a ``view`` at
``x0, y0`` with optional draw kwargs, which merge over five levels, the most specific winning::

    [visualization.kwargs]                 flat keys: every plot
    [visualization.kwargs.<plot>]          one plot type
    [[visualization.videos]].kwargs        flat keys: every panel of that video
    [[visualization.videos]].kwargs.<plot> one plot type in that video
    the panel's own keys

``palette`` tables (limb -> colour) merge key by key."""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

from ..errors import ConfigError, did_you_mean
from ..paths import name_problem

if TYPE_CHECKING:  # pragma: no cover
    from ..config import Config

PLOTS = ("imshow", "skeleton_2d", "skeleton_3d")

#: Draw kwargs and their values when no level sets them.
DEFAULT_DRAW_KWARGS: dict[str, Any] = {
    "point_radius": 3,
    "line_thickness": 2,
    "scale": 1.0,
    "width": None,
    "height": None,
    "palette": {},
    "background": None,
}

#: Output rate used when neither the config nor the footage gives a plausible one.
DEFAULT_FPS = 30.0
#: Container frame rates outside this range are treated as metadata errors.
PLAUSIBLE_FPS = (1.0, 10_000.0)

_TOP_KEYS = {"background", "kwargs", "videos", "output_fps", "speed", "default_fps", "labels"}
_VIDEO_KEYS = {
    "video_name",
    "name",
    "panels",
    "kwargs",
    "width",
    "height",
    "background",
    "output_fps",
    "speed",
}
_PANEL_KEYS = {"plot", "view", "x0", "y0"} | set(DEFAULT_DRAW_KWARGS)

RGB = tuple[int, int, int]


def parse_color(value: Any, where: str) -> RGB:
    """A matplotlib colour (``"black"``, ``"#ba1e31"``, ``"C3"``) or ``[r, g, b]`` (0-255) as RGB."""
    if isinstance(value, (list, tuple)):
        if len(value) == 3 and all(isinstance(c, (int, float)) and 0 <= c <= 255 for c in value):
            return tuple(int(round(c)) for c in value)  # type: ignore[return-value]
        raise ConfigError(f"{where}: {value!r} is not a colour; give [r, g, b] with values 0-255")
    if isinstance(value, str) and re.fullmatch("#[0-9a-fA-F]{6}|black|white", value):
        value = {"black": "#000000", "white": "#ffffff"}.get(value, value)  # no matplotlib: ~0.2 s
        return tuple(int(value[i : i + 2], 16) for i in (1, 3, 5))  # type: ignore[return-value]
    from matplotlib.colors import to_rgb

    try:
        r, g, b = to_rgb(value)
    except (ValueError, TypeError):
        raise ConfigError(
            f"{where}: {value!r} is not a colour; use a name ('black'), '#rrggbb' or [r, g, b]"
        ) from None
    return (int(round(r * 255)), int(round(g * 255)), int(round(b * 255)))


@dataclass(frozen=True)
class PanelSpec:
    """One panel: ``plot`` (``imshow`` the view's frame, ``skeleton_2d`` its 2D, ``skeleton_3d``
    the 3D reprojected) of ``view`` with its top-left corner at ``x0, y0``, sizes in canvas pixels
    (:meth:`size`). ``background`` ``None``: a transparent overlay (an ``imshow`` panel without
    footage uses the video's); ``where``: the config key, for error messages."""

    plot: str
    view: str
    x0: int
    y0: int
    point_radius: int = 3
    line_thickness: int = 2
    scale: float = 1.0
    width: int | None = None
    height: int | None = None
    palette: dict[str, RGB] = field(default_factory=dict)
    background: RGB | None = None
    where: str = "panel"

    def size(self, image_hw: tuple[int, int]) -> tuple[int, int]:
        """Panel ``(width, height)`` in pixels for frames of ``image_hw``: ``width`` and
        ``height``, the frame's aspect ratio filling in a missing one (neither: the frame size),
        then times ``scale``."""
        img_h, img_w = image_hw
        if self.width is not None and self.height is not None:
            w, h = float(self.width), float(self.height)
        elif self.width is not None:
            w, h = float(self.width), self.width * img_h / img_w
        elif self.height is not None:
            w, h = self.height * img_w / img_h, float(self.height)
        else:
            w, h = float(img_w), float(img_h)
        return max(1, int(round(w * self.scale))), max(1, int(round(h * self.scale)))

    def static_size(self) -> tuple[int, int] | None:
        """The panel size when it does not depend on the frame size, else ``None``."""
        if self.width is None or self.height is None:
            return None
        return self.size((self.height, self.width))


@dataclass(frozen=True)
class VideoSpec:
    """One output video (``<outdir>/<name>.mp4``): panels in drawing order, canvas and rate
    (``output_fps`` or ``speed``, a multiple of the input rate; neither: the recording's).
    ``labels``: view names and the frame stamp written on the canvas."""

    name: str
    panels: tuple[PanelSpec, ...]
    width: int | None = None
    height: int | None = None
    background: RGB = (0, 0, 0)
    output_fps: float | None = None
    speed: float | None = None
    where: str = "video"
    labels: bool = True

    @property
    def views(self) -> list[str]:
        """Views used by any panel, in first-use order."""
        return list(dict.fromkeys(p.view for p in self.panels))

    def canvas_size(self, image_sizes: Mapping[str, tuple[int, int]]) -> tuple[int, int]:
        """Canvas ``(width, height)`` for raw frames of ``view -> (height, width)``: the explicit
        size (a panel past it is a :class:`ConfigError`), else the union of the panels from the
        origin, rounded up to even sizes."""
        rects = [(p, *p.size(image_sizes[p.view])) for p in self.panels]
        # an automatic size is rounded up to even: H.264 in 4:2:0 needs even sizes
        width = self.width or _even_up(max((p.x0 + w for p, w, _ in rects), default=2))
        height = self.height or _even_up(max((p.y0 + h for p, _, h in rects), default=2))
        for p, w, h in rects:
            if p.x0 + w > width or p.y0 + h > height:
                raise ConfigError(
                    f"{p.where}: panel {w}x{h} at ({p.x0}, {p.y0}) runs off the "
                    f"{width}x{height} canvas; move it, shrink it or enlarge "
                    f"{self.where}.width/height"
                )
        return width, height


def _even_up(n: int) -> int:
    return n + (n & 1)


def merge_draw_kwargs(*levels: Mapping[str, Any]) -> dict[str, Any]:
    """Merge draw kwargs, later levels winning; ``palette`` tables merge key by key."""
    out = dict(DEFAULT_DRAW_KWARGS)
    out["palette"] = {}
    for level in levels:
        for key, value in level.items():
            if key == "palette":
                out["palette"] = {**out["palette"], **dict(value)}
            else:
                out[key] = value
    return out


def _split_kwargs(table: Any, where: str) -> tuple[dict, dict[str, dict]]:
    """Split a kwargs table into flat draw kwargs and per-plot subtables, validating keys."""
    if table is None:
        return {}, {}
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where} must be a table of draw kwargs, got {type(table).__name__}")
    flat: dict = {}
    per_plot: dict[str, dict] = {}
    for key, value in table.items():
        if key in PLOTS:
            if not isinstance(value, Mapping):
                raise ConfigError(f"{where}.{key} must be a table of draw kwargs")
            for sub in value:
                _check_draw_key(sub, f"{where}.{key}")
            _check_palette(value, f"{where}.{key}")
            per_plot[key] = dict(value)
        else:
            _check_draw_key(key, where)
            flat[key] = value
    _check_palette(flat, where)
    return flat, per_plot


def _check_draw_key(key: str, where: str) -> None:
    if key not in DEFAULT_DRAW_KWARGS:
        raise ConfigError(
            f"{where}: unknown key {key!r}; {did_you_mean(key, [*PLOTS, *DEFAULT_DRAW_KWARGS])}plot names are {', '.join(PLOTS)} and draw "
            f"kwargs are {', '.join(DEFAULT_DRAW_KWARGS)}"
        )


def _check_keys(table: Mapping, known: set[str], where: str) -> None:
    for key in table:
        if key not in known:
            raise ConfigError(
                f"{where}: unknown key {key!r}; {did_you_mean(key, known)}known: {sorted(known)}"
            )


def _check_palette(table: Mapping, where: str) -> None:
    if "palette" in table and not isinstance(table["palette"], Mapping):
        raise ConfigError(f"{where}.palette must be a table limb -> colour")


def _number(value: Any, where: str, *, integer: bool, minimum: float, allow_none: bool = False):
    if value is None and allow_none:
        return None
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and integer:
        ok = float(value).is_integer()
    if not ok or value < minimum:
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"{where} must be {kind} >= {minimum:g}, got {value!r}")
    return int(value) if integer else float(value)


def _rate(table: Mapping, where: str) -> tuple[float | None, float | None]:
    fps = _number(
        table.get("output_fps"), f"{where}.output_fps", integer=False, minimum=1e-9, allow_none=True
    )
    speed = _number(
        table.get("speed"), f"{where}.speed", integer=False, minimum=1e-9, allow_none=True
    )
    if fps is not None and speed is not None:
        raise ConfigError(f"{where}: give output_fps or speed, not both")
    return fps, speed


def video_specs(config: Config) -> list[VideoSpec]:
    """The output videos ``config`` asks for, views checked against its ``cameras`` table."""
    cameras = config.data.get("cameras")
    views = [k for k in cameras if k != "defaults"] if isinstance(cameras, Mapping) else None
    return read_video_specs(config.visualization, view_names=views)


def read_video_specs(
    table: Mapping[str, Any] | None, view_names: Sequence[str] | None = None
) -> list[VideoSpec]:
    """Parse and validate ``[[visualization.videos]]`` (the ``visualization`` table) into one
    :class:`VideoSpec` per video, draw kwargs merged; views are checked when ``view_names`` is
    given. A bad key is a :class:`ConfigError` naming ``visualization.videos[i].panels[j]``."""
    table = {} if table is None else table
    if not isinstance(table, Mapping):
        raise ConfigError("visualization must be a table")
    _check_keys(table, _TOP_KEYS, "visualization")
    background = parse_color(table.get("background", "black"), "visualization.background")
    labels = table.get("labels", True)
    if not isinstance(labels, bool):
        raise ConfigError(f"visualization.labels: expected true or false, got {labels!r}")
    global_flat, global_plot = _split_kwargs(table.get("kwargs"), "visualization.kwargs")
    default_fps(table)  # validate early
    _rate(table, "visualization")
    videos = table.get("videos", []) or []
    if not isinstance(videos, Sequence) or isinstance(videos, (str, bytes)):
        raise ConfigError("visualization.videos must be a list of video tables")
    specs: list[VideoSpec] = []
    seen: set[str] = set()
    for i, video in enumerate(videos):
        spec = _read_video(
            video, f"visualization.videos[{i}]", background, global_flat, global_plot, view_names
        )
        spec = replace(spec, labels=labels)
        if spec.name in seen:
            raise ConfigError(
                f"{spec.where}: video_name {spec.name!r} is used twice; "
                "each video needs its own name"
            )
        seen.add(spec.name)
        specs.append(spec)
    return specs


def _read_video(
    video: Any,
    where: str,
    background: RGB,
    global_flat: dict,
    global_plot: dict,
    view_names: Sequence[str] | None,
) -> VideoSpec:
    if not isinstance(video, Mapping):
        raise ConfigError(f"{where} must be a table with video_name and panels")
    _check_keys(video, _VIDEO_KEYS, where)
    name = video.get("video_name", video.get("name"))
    if not isinstance(name, str) or not name or name_problem(name):
        raise ConfigError(f"{where}.video_name must be a non-empty file stem, got {name!r}")
    width = _number(video.get("width"), f"{where}.width", integer=True, minimum=2, allow_none=True)
    height = _number(
        video.get("height"), f"{where}.height", integer=True, minimum=2, allow_none=True
    )
    if "background" in video:
        background = parse_color(video["background"], f"{where}.background")
    fps, speed = _rate(video, where)
    video_flat, video_plot = _split_kwargs(video.get("kwargs"), f"{where}.kwargs")
    panels_raw = video.get("panels")
    if (
        not isinstance(panels_raw, Sequence)
        or isinstance(panels_raw, (str, bytes))
        or not panels_raw
    ):
        raise ConfigError(f"{where}.panels must be a non-empty list of panel tables")
    panels = []
    for j, raw in enumerate(panels_raw):
        pwhere = f"{where}.panels[{j}]"
        panel = _read_panel(
            raw, pwhere, view_names, global_flat, global_plot, video_flat, video_plot
        )
        _check_static_bounds(panel, width, height)
        panels.append(panel)
    return VideoSpec(
        name=name,
        panels=tuple(panels),
        width=width,
        height=height,
        background=background,
        output_fps=fps,
        speed=speed,
        where=where,
    )


def _read_panel(
    raw: Any, where: str, view_names, global_flat, global_plot, video_flat, video_plot
) -> PanelSpec:
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{where} must be a table {{plot, view, x0, y0, ...}}")
    _check_keys(raw, _PANEL_KEYS, where)
    plot = raw.get("plot")
    if plot not in PLOTS:
        raise ConfigError(f"{where}.plot: unknown plot {plot!r}; use one of {', '.join(PLOTS)}")
    view = raw.get("view")
    if not isinstance(view, str):
        raise ConfigError(f"{where}.view must name a camera of the rig, got {view!r}")
    if view_names is not None and view not in view_names:
        raise ConfigError(
            f"{where}.view: {view!r} is not a view of the rig; use one of {', '.join(view_names)}"
        )
    own = {k: v for k, v in raw.items() if k in DEFAULT_DRAW_KWARGS}
    _check_palette(own, where)
    kw = merge_draw_kwargs(
        global_flat, global_plot.get(plot, {}), video_flat, video_plot.get(plot, {}), own
    )
    x0 = raw.get("x0", 0)
    y0 = raw.get("y0", 0)
    for key, value in (("x0", x0), ("y0", y0)):
        if not (isinstance(value, int) and not isinstance(value, bool)):
            raise ConfigError(f"{where}.{key} must be an integer pixel offset, got {value!r}")
        if value < 0:
            raise ConfigError(
                f"{where}: panel is off the canvas ({key} = {value} < 0); use offsets >= 0"
            )
    palette = {
        str(limb): parse_color(c, f"{where}.palette.{limb}") for limb, c in kw["palette"].items()
    }
    bg = None if kw["background"] is None else parse_color(kw["background"], f"{where}.background")
    return PanelSpec(
        plot=plot,
        view=view,
        x0=x0,
        y0=y0,
        point_radius=_number(kw["point_radius"], f"{where}.point_radius", integer=True, minimum=0),
        line_thickness=_number(
            kw["line_thickness"], f"{where}.line_thickness", integer=True, minimum=1
        ),
        scale=_number(kw["scale"], f"{where}.scale", integer=False, minimum=1e-6),
        width=_number(kw["width"], f"{where}.width", integer=True, minimum=1, allow_none=True),
        height=_number(kw["height"], f"{where}.height", integer=True, minimum=1, allow_none=True),
        palette=palette,
        background=bg,
        where=where,
    )


def _check_static_bounds(panel: PanelSpec, width: int | None, height: int | None) -> None:
    """Reject panels that are off an explicitly sized canvas before any footage is read."""
    size = panel.static_size() or (1, 1)
    for origin, extent, limit, axis in (
        (panel.x0, size[0], width, "width"),
        (panel.y0, size[1], height, "height"),
    ):
        if limit is not None and origin + extent > limit:
            raise ConfigError(
                f"{panel.where}: panel is off the canvas ({origin} + {extent} > {axis} "
                f"{limit}); move or shrink it, or enlarge the video's {axis}"
            )


def default_fps(table: Mapping) -> float:
    """``visualization.default_fps`` (30 unless set), validated."""
    return _number(
        table.get("default_fps", DEFAULT_FPS),
        "visualization.default_fps",
        integer=False,
        minimum=1e-9,
    )


def resolve_output_fps(
    video: VideoSpec, table: Mapping, input_fps: float | None, speed: float | None = None
) -> float:
    """The frame rate to encode ``video`` at: its ``output_fps``/``speed``, the global ones, the
    ``speed`` argument, else the recording's rate. ``speed`` multiplies the input rate; one unknown
    or outside :data:`PLAUSIBLE_FPS` (the DeepFly3D sample says 0.2 fps) is replaced by
    ``visualization.default_fps`` with a warning."""
    default_speed = speed
    fps, speed = video.output_fps, video.speed
    if fps is None and speed is None:
        fps, speed = _rate(table, "visualization")
    if fps is None and speed is None:
        speed = default_speed
    if fps is not None:
        return fps
    base = input_fps
    if base is None or not (PLAUSIBLE_FPS[0] <= base <= PLAUSIBLE_FPS[1]):
        fallback = default_fps(table)
        reason = "unknown" if base is None else f"{base:g} fps, not plausible"
        warnings.warn(
            f"{video.where} ({video.name}): the footage frame rate is {reason}; writing at "
            f"visualization.default_fps = {fallback:g} fps (set output_fps to choose)",
            stacklevel=2,
        )
        base = fallback
    return base * (speed if speed is not None else 1.0)
