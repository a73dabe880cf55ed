"""The detection plan: sources -> preprocessors -> models -> pathways -> (view, point).

Also the preprocessing ops: each transforms an image batch (in torch, so frames stay on the GPU)
and 2D points, and inverts exactly on points, so a pathway's detections map back into its
source's raw frame. The ops' point methods use the pixel-centre convention: pixel ``(i, j)``
(row, column) has centre ``(x, y) = (j, i)``; a ``W``-wide image spans ``x`` in
``[-0.5, W - 0.5]``. Under it a horizontal mirror is ``x -> W - 1 - x`` and a resize by ``s`` is
``x -> (x + 0.5) s - 0.5`` (what ``torch.nn.functional.interpolate`` with
``align_corners=False`` does to pixels).

Heatmap cells map to raw-frame pixels with DeepFly2D's convention, the one the published weights
were trained with and DeepFly3D stores its 2D in (``../shared/spec/deepfly2d-heatmap-decoding.md``):
cell ``(r, c)`` of an ``H_hm x W_hm`` heatmap is the normalized point ``(c / W_hm, r / H_hm)`` of
the model input, with no half-cell shift, and a normalized point ``u`` of a ``W``-wide image is
the pixel value ``u W``. That is the edge-based form of the ops above (``u W = x + 0.5``): a
mirror is ``u -> 1 - u``, a resize keeps ``u``. On a pathway without preprocessing, cell
``(r, c)`` is raw ``(c / W_hm W_raw, r / H_hm H_raw)``; through the ``fliplr`` preprocessor,
``((1 - c / W_hm) W_raw, r / H_hm H_raw)``.

Torch is imported only inside the image functions, so the plan (e.g.
:meth:`DetectionPlan.view_sources`) can be read without it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..config.constants import SUBPIXEL_METHODS
from ..errors import ConfigError

Size = tuple[int, int]  # (height, width)

#: The seed system's default: the intensity-weighted centroid of the 5x5 window.
DEFAULT_SUBPIXEL = "weighted"
#: How heatmap cells become raw pixels (part of pose2d's stage parameters, so 2D detected under an
#: earlier convention is recomputed, never reused).
DECODING_CONVENTION = "deepfly2d-normalized-cells"


# --- preprocessing ops ------------------------------------------------------------------


class Op:
    """One geometric frame op: image batch forward, points forward and inverse."""

    def out_size(self, size: Size) -> Size:
        """``(height, width)`` after the op, given the size before."""
        return size

    def forward_points(self, xy: np.ndarray, size: Size) -> np.ndarray:
        """Map ``(..., 2)`` points of a ``size`` image into the op's output image."""
        raise NotImplementedError

    def inverse_points(self, xy: np.ndarray, size: Size) -> np.ndarray:
        """Map ``(..., 2)`` points of the op's output back into the ``size`` input image."""
        raise NotImplementedError

    def apply(self, images):
        """Apply the op to a torch batch ``(N, C, H, W)``."""
        raise NotImplementedError


@dataclass(frozen=True)
class FlipLR(Op):
    """Mirror left-right (``x -> W - 1 - x``)."""

    def forward_points(self, xy, size):
        out = np.array(xy, dtype=np.float64, copy=True)
        out[..., 0] = (size[1] - 1) - out[..., 0]
        return out

    inverse_points = forward_points

    def apply(self, images):
        return images.flip(-1)


@dataclass(frozen=True)
class FlipUD(Op):
    """Mirror top-bottom (``y -> H - 1 - y``)."""

    def forward_points(self, xy, size):
        out = np.array(xy, dtype=np.float64, copy=True)
        out[..., 1] = (size[0] - 1) - out[..., 1]
        return out

    inverse_points = forward_points

    def apply(self, images):
        return images.flip(-2)


@dataclass(frozen=True)
class Rot90(Op):
    """Rotate by ``k`` quarter turns counter-clockwise, as :func:`numpy.rot90` does."""

    k: int = 1

    def out_size(self, size):
        return size if self.k % 2 == 0 else (size[1], size[0])

    def _once(self, xy, size):
        # one CCW quarter turn of an (H, W) image: (x, y) -> (y, W - 1 - x)
        return np.stack([xy[..., 1], (size[1] - 1) - xy[..., 0]], axis=-1)

    def _once_inverse(self, xy, size):
        # `size` is the image before the turn; output is (W, H)
        return np.stack([(size[1] - 1) - xy[..., 1], xy[..., 0]], axis=-1)

    def forward_points(self, xy, size):
        out = np.asarray(xy, dtype=np.float64)
        for _ in range(self.k % 4):
            out = self._once(out, size)
            size = (size[1], size[0])
        return out

    def inverse_points(self, xy, size):
        sizes = [size]
        for _ in range(self.k % 4):
            sizes.append((sizes[-1][1], sizes[-1][0]))
        out = np.asarray(xy, dtype=np.float64)
        for s in reversed(sizes[:-1]):
            out = self._once_inverse(out, s)
        return out

    def apply(self, images):
        import torch

        return torch.rot90(images, self.k % 4, dims=(-2, -1))


@dataclass(frozen=True)
class Crop(Op):
    """Keep the ``height x width`` window whose top-left pixel is ``(x0, y0)``."""

    x0: int
    y0: int
    width: int
    height: int

    def check(self, size: Size, where: str) -> None:
        """Raise :class:`ConfigError` if the window leaves a ``size`` frame."""
        if self.x0 + self.width > size[1] or self.y0 + self.height > size[0]:
            raise ConfigError(
                f"{where}: crop x0={self.x0} y0={self.y0} {self.width}x{self.height} leaves the "
                f"{size[1]}x{size[0]} frame; shrink the crop"
            )

    def out_size(self, size):
        return (self.height, self.width)

    def forward_points(self, xy, size):
        return np.asarray(xy, dtype=np.float64) - np.array([self.x0, self.y0], dtype=np.float64)

    def inverse_points(self, xy, size):
        return np.asarray(xy, dtype=np.float64) + np.array([self.x0, self.y0], dtype=np.float64)

    def apply(self, images):
        return images[..., self.y0 : self.y0 + self.height, self.x0 : self.x0 + self.width]


@dataclass(frozen=True)
class Resize(Op):
    """Resample to ``height x width`` (bilinear, antialiased when shrinking)."""

    height: int
    width: int

    def out_size(self, size):
        return (self.height, self.width)

    def _scale(self, size):
        return np.array([self.width / size[1], self.height / size[0]], dtype=np.float64)

    def forward_points(self, xy, size):
        return (np.asarray(xy, dtype=np.float64) + 0.5) * self._scale(size) - 0.5

    def inverse_points(self, xy, size):
        return (np.asarray(xy, dtype=np.float64) + 0.5) / self._scale(size) - 0.5

    def apply(self, images):
        from torch.nn import functional as F

        if tuple(images.shape[-2:]) == (self.height, self.width):
            return images
        shrinking = images.shape[-2] > self.height or images.shape[-1] > self.width
        return F.interpolate(
            images,
            size=(self.height, self.width),
            mode="bilinear",
            align_corners=False,
            antialias=shrinking,
        )


def _int(spec: Mapping, key: str, where: str, *, minimum: int = 0) -> int:
    if key not in spec:
        raise ConfigError(f"{where}: missing key {key!r}")
    value = spec[key]
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ConfigError(f"{where}.{key}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def parse_op(spec: Mapping, where: str) -> Op:
    """Build one op from its config entry (``{op: fliplr}``, ``{op: crop, x0, y0, width,
    height}``...); :class:`ConfigError` for an unknown op or a missing/invalid parameter."""
    if not isinstance(spec, Mapping) or "op" not in spec:
        raise ConfigError(f"{where}: each op must be a table with an 'op' key, got {spec!r}")
    kind = str(spec["op"]).lower()
    allowed = {"op"}
    if kind == "fliplr":
        op: Op = FlipLR()
    elif kind == "flipud":
        op = FlipUD()
    elif kind == "rot90":
        allowed |= {"k"}
        op = Rot90(k=_int(spec, "k", where) % 4 if "k" in spec else 1)
    elif kind == "crop":
        allowed |= {"x0", "y0", "width", "height"}
        op = Crop(
            _int(spec, "x0", where),
            _int(spec, "y0", where),
            _int(spec, "width", where, minimum=1),
            _int(spec, "height", where, minimum=1),
        )
    elif kind == "resize":
        allowed |= {"width", "height"}
        op = Resize(_int(spec, "height", where, minimum=1), _int(spec, "width", where, minimum=1))
    else:
        raise ConfigError(
            f"{where}.op: unknown op {spec['op']!r}; use fliplr, flipud, rot90, crop or resize"
        )
    extra = set(spec) - allowed
    if extra:
        raise ConfigError(f"{where}: unknown key(s) {sorted(extra)} for op {kind!r}")
    return op


# --- the plan -----------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelSpec:
    """A detector model entry of ``[[pose2d.models]]``."""

    name: str
    model_class: str
    weights: str
    input_size: Size
    mean: float
    std: float
    n_out_channels: int
    url: str | None = None
    sha256: str | None = None
    subpixel: str = DEFAULT_SUBPIXEL


@dataclass(frozen=True)
class Pathway:
    """One ``source -> preprocessor -> model`` run: ``channels[i]`` of the model output fills
    ``(views[i], points[i])`` of the ``(V, T, P)`` arrays."""

    name: str
    source: str
    model: str
    preprocessor: str | None
    ops: tuple[Op, ...]
    channels: np.ndarray = field(repr=False)
    views: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)

    def input_ops(self, model: ModelSpec) -> tuple[Op, ...]:
        """The ops from a raw frame to the model input (the preprocessor, then the resize)."""
        return (*self.ops, Resize(*model.input_size))

    def _sizes(self, raw_size: Size, model: ModelSpec) -> tuple[tuple[Op, ...], list[Size]]:
        ops = self.input_ops(model)
        sizes = [tuple(raw_size)]
        for op in ops:
            sizes.append(op.out_size(sizes[-1]))
        return ops, sizes

    def heatmap_to_raw(
        self, xy: np.ndarray, raw_size: Size, model: ModelSpec, heatmap_size: Size
    ) -> np.ndarray:
        """Map ``(..., 2)`` heatmap cells ``(x, y) = (column, row)`` (fractional after sub-pixel
        refinement) of ``(H_hm, W_hm)`` = ``heatmap_size`` heatmaps to float64 pixels ``(x, y)`` of
        the ``(height, width)`` = ``raw_size`` raw source frame. DeepFly2D's convention (module
        docstring): cell ``c`` is the normalized point ``c / W_hm`` of the model input, and the raw
        pixel is the normalized raw-frame point times the frame size."""
        ops, sizes = self._sizes(raw_size, model)
        cells = np.array(heatmap_size[::-1], dtype=np.float64)  # (W_hm, H_hm)
        pixels = np.array(sizes[-1][::-1], dtype=np.float64)  # model input (W, H)
        # normalized -> the model input's pixel-centre coordinates, where the ops work
        out = np.asarray(xy, dtype=np.float64) / cells * pixels - 0.5
        for op, size in zip(reversed(ops), reversed(sizes[:-1])):
            out = op.inverse_points(out, size)
        return out + 0.5

    def raw_to_heatmap(
        self, xy: np.ndarray, raw_size: Size, model: ModelSpec, heatmap_size: Size
    ) -> np.ndarray:
        """Map raw-frame ``(..., 2)`` points onto heatmap cells (inverse of :meth:`heatmap_to_raw`)."""
        ops, sizes = self._sizes(raw_size, model)
        out = np.asarray(xy, dtype=np.float64) - 0.5
        for op, size in zip(ops, sizes[:-1]):
            out = op.forward_points(out, size)
        cells = np.array(heatmap_size[::-1], dtype=np.float64)
        pixels = np.array(sizes[-1][::-1], dtype=np.float64)
        return (out + 0.5) / pixels * cells

    def check_frame(self, raw_size: Size) -> None:
        """Raise :class:`ConfigError` if a crop of this pathway leaves a ``raw_size`` frame."""
        size = tuple(raw_size)
        for op in self.ops:
            if isinstance(op, Crop):
                op.check(size, f"pose2d.preprocessors[{self.preprocessor}] (pathway {self.name})")
            size = op.out_size(size)


def _table_list(value, where: str) -> list[Mapping]:
    if value is None:
        return []
    if not isinstance(value, Sequence) or isinstance(value, (str, bytes)):
        raise ConfigError(f"{where}: expected a list of tables, got {type(value).__name__}")
    for i, item in enumerate(value):
        if not isinstance(item, Mapping) or "name" not in item:
            raise ConfigError(f"{where}[{i}]: expected a table with a 'name', got {item!r}")
    return list(value)


def _unique_names(entries: list[Mapping], where: str) -> None:
    seen: set[str] = set()
    for entry in entries:
        name = str(entry["name"])
        if name in seen:
            raise ConfigError(f"{where}: the name {name!r} is used twice")
        seen.add(name)


def _parse_model(entry: Mapping, where: str) -> ModelSpec:
    cls = str(entry.get("class", "hourglass"))
    if cls != "hourglass":
        raise ConfigError(
            f"{where}.class: unknown model class {cls!r}; only 'hourglass' is supported"
        )
    size = entry.get("input_size", [256, 512])
    if not (
        isinstance(size, Sequence)
        and len(size) == 2
        and all(isinstance(s, int) and s > 0 for s in size)
    ):
        raise ConfigError(f"{where}.input_size: expected [height, width], got {size!r}")
    if size[0] % 64 or size[1] % 64:
        raise ConfigError(
            f"{where}.input_size: {list(size)} must be multiples of 64 for the hourglass"
        )
    n_out = entry.get("n_out_channels")
    if not isinstance(n_out, int) or isinstance(n_out, bool) or n_out < 1:
        raise ConfigError(f"{where}.n_out_channels: expected a positive integer, got {n_out!r}")
    try:
        mean, std = float(entry.get("mean", 0.0)), float(entry.get("std", 1.0))
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: mean and std must be numbers") from None
    if std <= 0:
        raise ConfigError(f"{where}.std: must be positive, got {std}")
    subpixel = check_subpixel(entry.get("subpixel", DEFAULT_SUBPIXEL), f"{where}.subpixel")
    return ModelSpec(
        name=str(entry["name"]),
        model_class=cls,
        weights=str(entry.get("weights") or ""),
        input_size=(int(size[0]), int(size[1])),
        mean=mean,
        std=std,
        n_out_channels=n_out,
        url=entry.get("url") or None,
        sha256=entry.get("sha256") or None,
        subpixel=subpixel,
    )


def check_subpixel(method: str, where: str = "pose2d.models[].subpixel") -> str:
    """``method`` if it is one of :data:`SUBPIXEL_METHODS`, else a :class:`~flylib.errors.ConfigError`."""
    if method not in SUBPIXEL_METHODS:
        raise ConfigError(
            f"{where}: unknown sub-pixel method {method!r}; use one of {', '.join(SUBPIXEL_METHODS)}"
        )
    return method


def _parse_preprocessors(pose2d: Mapping) -> dict[str, tuple[Op, ...]]:
    """``pose2d.preprocessors``: name -> its ops."""
    pre_entries = _table_list(pose2d.get("preprocessors"), "pose2d.preprocessors")
    _unique_names(pre_entries, "pose2d.preprocessors")
    preprocessors = {}
    for i, entry in enumerate(pre_entries):
        ops = entry.get("ops") or []
        if not isinstance(ops, Sequence) or isinstance(ops, (str, bytes)):
            raise ConfigError(f"pose2d.preprocessors[{i}].ops: expected a list of op tables")
        preprocessors[str(entry["name"])] = tuple(
            parse_op(op, f"pose2d.preprocessors[{i}].ops[{j}]") for j, op in enumerate(ops)
        )
    return preprocessors


def _parse_models(pose2d: Mapping) -> dict[str, ModelSpec]:
    """``pose2d.models``, with the checkpoints ``pose2d.weights`` sets."""
    model_entries = _table_list(pose2d.get("models"), "pose2d.models")
    _unique_names(model_entries, "pose2d.models")
    models = {
        str(e["name"]): _parse_model(e, f"pose2d.models[{i}]") for i, e in enumerate(model_entries)
    }
    # pose2d.weights: {model: path} sets a checkpoint without restating the model entry
    for name, path in (pose2d.get("weights") or {}).items():
        if name not in models:
            raise ConfigError(
                f"pose2d.weights.{name}: unknown model {name!r}; defined: {sorted(models)}"
            )
        models[name] = replace(models[name], weights=str(path or ""))
    return models


@dataclass(frozen=True)
class DetectionPlan:
    """The parsed, validated 2D detection plan: ``sources`` (name -> footage pattern of
    ``[[sources]]``, config order), ``models`` (name -> :class:`ModelSpec`), ``pathways`` (config
    order), ``view_names`` (the V axis: cameras in config order), ``point_names`` (the P axis)."""

    sources: dict[str, str]
    models: dict[str, ModelSpec]
    pathways: tuple[Pathway, ...]
    view_names: tuple[str, ...]
    point_names: tuple[str, ...]
    preprocessors: dict[str, tuple[Op, ...]]

    @classmethod
    def from_tables(
        cls,
        sources: Sequence[Mapping] | None,
        pose2d: Mapping | None,
        view_names: Sequence[str],
        point_names: Sequence[str],
    ) -> DetectionPlan:
        """Parse the plan from the config's ``sources`` list (``{name, filename?}`` entries) and
        ``pose2d`` table (its ``preprocessors``, ``models``, ``weights``, ``pathways`` and
        ``output_points``), on the rig's views (V) and the skeleton's points (P), in order.

        A :class:`ConfigError` names the offending key for any inconsistency (unknown source,
        model, preprocessor, view or point; a channel beyond the model's outputs; one view fed from
        two different sources).
        """
        pose2d = pose2d or {}
        if not isinstance(pose2d, Mapping):
            raise ConfigError("pose2d: expected a table")

        source_entries = _table_list(sources, "sources")
        _unique_names(source_entries, "sources")
        patterns = {str(e["name"]): str(e.get("filename") or e["name"]) for e in source_entries}

        preprocessors = _parse_preprocessors(pose2d)
        models = _parse_models(pose2d)

        output_points = pose2d.get("output_points") or {}
        if not isinstance(output_points, Mapping):
            raise ConfigError(
                "pose2d.output_points: expected a table of view -> point -> {pathway, out_channel}"
            )
        view_names, point_names = [str(v) for v in view_names], [str(p) for p in point_names]
        view_index = {v: i for i, v in enumerate(view_names)}
        point_index = {p: i for i, p in enumerate(point_names)}

        path_entries = _table_list(pose2d.get("pathways"), "pose2d.pathways")
        _unique_names(path_entries, "pose2d.pathways")
        raw: dict[str, dict] = {}
        for i, entry in enumerate(path_entries):
            where = f"pose2d.pathways[{i}] ({entry['name']})"
            src, model = entry.get("source"), entry.get("model")
            pre = entry.get("preprocessor") or None
            if src not in patterns:
                raise ConfigError(
                    f"{where}.source: unknown source {src!r}; defined: {sorted(patterns)}"
                )
            if model not in models:
                raise ConfigError(
                    f"{where}.model: unknown model {model!r}; defined: {sorted(models)}"
                )
            if pre is not None and pre not in preprocessors:
                raise ConfigError(
                    f"{where}.preprocessor: unknown preprocessor {pre!r}; defined: {sorted(preprocessors)}"
                )
            raw[str(entry["name"])] = dict(source=src, model=model, preprocessor=pre, slots=[])

        view_source: dict[str, str] = {}
        for view, table in output_points.items():
            view = str(view)
            if view not in view_index:
                raise ConfigError(
                    f"pose2d.output_points.{view}: unknown view; cameras are {view_names}"
                )
            if not isinstance(table, Mapping):
                raise ConfigError(
                    f"pose2d.output_points.{view}: expected a table of point -> {{pathway, out_channel}}"
                )
            for point, slot in table.items():
                where = f"pose2d.output_points.{view}.{point}"
                if point not in point_index:
                    raise ConfigError(f"{where}: unknown skeleton point {point!r}")
                if (
                    not isinstance(slot, Mapping)
                    or "pathway" not in slot
                    or "out_channel" not in slot
                ):
                    raise ConfigError(f"{where}: expected {{pathway, out_channel}}, got {slot!r}")
                pathway = raw.get(slot["pathway"])
                if pathway is None:
                    raise ConfigError(
                        f"{where}.pathway: unknown pathway {slot['pathway']!r}; defined: {sorted(raw)}"
                    )
                channel = slot["out_channel"]
                n_out = models[pathway["model"]].n_out_channels
                if (
                    not isinstance(channel, int)
                    or isinstance(channel, bool)
                    or not 0 <= channel < n_out
                ):
                    raise ConfigError(
                        f"{where}.out_channel: {channel!r} is not a channel of model "
                        f"{pathway['model']!r} (0..{n_out - 1})"
                    )
                previous = view_source.setdefault(view, pathway["source"])
                if previous != pathway["source"]:
                    raise ConfigError(
                        f"{where}: view {view!r} takes points from sources {previous!r} and "
                        f"{pathway['source']!r}; a view's pixels must all come from one source"
                    )
                pathway["slots"].append((channel, view_index[view], point_index[point]))

        pathways = []
        for name, info in raw.items():
            slots = np.array(info["slots"], dtype=np.int64).reshape(-1, 3)
            pathways.append(
                Pathway(
                    name=name,
                    source=info["source"],
                    model=info["model"],
                    preprocessor=info["preprocessor"],
                    ops=preprocessors.get(info["preprocessor"], ()),
                    channels=slots[:, 0],
                    views=slots[:, 1],
                    points=slots[:, 2],
                )
            )
        return cls(
            sources=patterns,
            models=models,
            pathways=tuple(pathways),
            view_names=tuple(view_names),
            point_names=tuple(point_names),
            preprocessors=preprocessors,
        )

    def view_sources(self) -> dict[str, str]:
        """Which source's footage each view's pixels live in (views the plan fills)."""
        out = {}
        for pathway in self.pathways:
            for v in pathway.views:
                out.setdefault(self.view_names[int(v)], pathway.source)
        return {v: out[v] for v in self.view_names if v in out}

    def active_pathways(self) -> tuple[Pathway, ...]:
        """Pathways that fill at least one (view, point)."""
        return tuple(p for p in self.pathways if len(p.channels))

    def active_sources(self) -> list[str]:
        """Sources read by the active pathways, in ``[[sources]]`` order."""
        used = {p.source for p in self.active_pathways()}
        return [s for s in self.sources if s in used]

    def pathways_on(self, source: str) -> tuple[Pathway, ...]:
        """Active pathways reading ``source``."""
        return tuple(p for p in self.active_pathways() if p.source == source)

    def filled_mask(self) -> np.ndarray:
        """``(V, P)`` bool: which (view, point) slots some pathway fills."""
        mask = np.zeros((len(self.view_names), len(self.point_names)), dtype=bool)
        for pathway in self.pathways:
            mask[pathway.views, pathway.points] = True
        return mask
