"""``pose2d.import``: take 2D keypoints from another tool instead of running the detector.

The result is the same :class:`flylib.results.Pose2dData` the detector produces, so every later
stage runs unchanged.

Config keys (``pose2d.import``, or the ``import`` of a ``recordings`` entry)::

    pose2d:
      import:
        format: deepfly3d        # deepfly3d | dlc_csv | dlc_h5 | deeplabcut | lightning_pose | sleap
        files: "{view}.csv"      # relative to the recording directory; see below
        keypoint_map: {}         # file keypoint name -> skeleton point name (null = drop)
        likelihood_threshold: 0.0  # confidence below it -> point missing (NaN)
        image_size: [480, 960]   # (height, width) fallback for views without footage
        view_points: plan        # plan: keep only the points the detection plan gives each view | all
        views: [rh, rm, ...]     # deepfly3d only: the view of each pickle camera (null = skip)
        individual: null         # dlc multi-animal: which individual
        track: null              # sleap: track index or name when several

``files``: ``deepfly3d`` takes one pickle for all views (a glob matching one file; default
``df3d_result*.pkl`` in the recording directory, its ``df3d/`` folder, then ``../<name>_df3d/``,
DeepFly3D's own output folder). Per-view formats take a pattern with ``{view}``, ``{index}``
(position in the config), ``{source}`` (footage source) or ``{stem}`` (footage file name without
extension) placeholders, globbing allowed (one match per view), or a mapping ``{view: path}`` for
every configured view (``null``: observed by nothing).

``keypoint_map``: without it a file name must equal a skeleton point name (DeepFly3D joint ``j``
defaults to fly38 point ``(j + 19) mod 38``). A file keypoint that maps to nothing is an error, so a
renamed body part is never silently dropped; map it to ``null`` to drop it on purpose.

``view_points: plan`` sets missing (NaN) the points the plan's ``pose2d.output_points`` does not
give a view, warning once per file (DeepFly3D 1.x writes all 38 joints in every camera); a view the
plan does not list keeps every point. Scores become confidences in [0, 1] (:func:`as_confidences`);
frame sizes come from the footage header, else ``image_size``; all views must have the same number
of frames, and as many as their footage when its count is known.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ImportFormatError, did_you_mean, unknown_key
from . import views as _views
from ._h5 import read_budget
from .df3d import df3d_joint_to_fly38, read_df3d_points2d, result_folders
from .dlc import ViewKeypoints, read_dlc_csv, read_dlc_h5
from .sleap import read_sleap_analysis

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float

log = logging.getLogger(__name__)

FORMATS = ("deepfly3d", "dlc_csv", "dlc_h5", "deeplabcut", "lightning_pose", "sleap")
_DEFAULT_FILES = {
    "dlc_csv": "{view}.csv",
    "deeplabcut": "{view}.csv",
    "lightning_pose": "{view}.csv",
    "dlc_h5": "{view}.h5",
    "sleap": "{view}.analysis.h5",
}
#: The keys a ``pose2d.import`` table may hold (the config reference lists each).
IMPORT_KEYS = {
    "format",
    "files",
    "keypoint_map",
    "likelihood_threshold",
    "image_size",
    "views",
    "individual",
    "track",
    "view_points",
}
#: ``pose2d.import.view_points`` values: the detection plan's points per view, or all.
VIEW_POINTS = ("plan", "all")


@dataclass(frozen=True)
class ImportTarget:
    """What imported 2D is placed on: views (the V axis, in order), skeleton points (the P axis),
    ``view -> footage source``, ``source -> footage glob`` and ``view -> plan points``."""

    views: tuple[str, ...]
    point_names: tuple[str, ...]
    view_sources: Mapping[str, str] = field(default_factory=dict)
    source_patterns: Mapping[str, str] = field(default_factory=dict)
    plan_points: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def footage_globs(self) -> dict[str, str | None]:
        """``view -> glob`` of its footage (:func:`flylib.interop.views.footage_files`)."""
        return {v: self.source_patterns.get(s) for v, s in self.view_sources.items()}

    def footage(self, recording_dir: Path) -> dict[str, list[Path]]:
        """Each view's footage files in ``recording_dir``."""
        return _views.footage_files(self.footage_globs(), recording_dir)

    def checked_views(self) -> list[str]:
        """The views; :class:`ImportFormatError` when there are none."""
        if not self.views:
            raise ImportFormatError(
                "config names no views (no cameras entries, no pose2d.output_points); define the rig's views"
            )
        return list(self.views)


def import_spec(spec: Mapping | None) -> dict:
    """The import spec ``spec`` (the recording's, else ``pose2d.import``), validated."""
    where = "pose2d.import"
    if not isinstance(spec, Mapping):
        raise ImportFormatError(f"{where} must be a mapping with at least 'format', got {spec!r}")
    spec = dict(spec)
    unknown = sorted(str(k) for k in set(spec) - IMPORT_KEYS)
    if unknown:
        raise ImportFormatError(
            f"{where}.{unknown[0]}: {unknown_key('key', unknown[0], sorted(IMPORT_KEYS))}"
        )
    fmt = spec.get("format")
    if fmt not in FORMATS:
        raise ImportFormatError(f"{where}.format is {fmt!r}; use one of {list(FORMATS)}")
    size = spec.get("image_size")
    if size is not None and (
        not isinstance(size, (list, tuple))
        or len(size) != 2
        or not all(isinstance(v, int) and v > 0 for v in size)
    ):
        raise ImportFormatError(
            f"{where}.image_size must be [height, width] in pixels, got {size!r}"
        )
    if spec.get("view_points", "plan") not in VIEW_POINTS:
        raise ImportFormatError(
            f"{where}.view_points is {spec['view_points']!r}; use plan (each view keeps the "
            "points the detection plan gives it) or all (keep every point the files hold)"
        )
    threshold = spec.get("likelihood_threshold")
    if threshold is not None and not isinstance(threshold, (int, float)):
        raise ImportFormatError(f"{where}.likelihood_threshold must be a number, got {threshold!r}")
    return spec


def _glob_one(recording_dir: Path, pattern: str, what: str) -> Path:
    path = Path(pattern)
    if (recording_dir / path).is_file():  # a file named cam[1].csv is that file
        matches = [recording_dir / path]
    elif path.is_absolute():
        matches = (
            sorted(path.parent.glob(path.name)) if any(c in path.name for c in "*?[") else [path]
        )
    else:
        matches = sorted(recording_dir.glob(pattern))
    matches = [m for m in matches if m.is_file()]
    if not matches:
        raise ImportFormatError(
            f"{recording_dir}: no file matches {pattern!r} for {what}; "
            f"{_closest_file(recording_dir, pattern)}"
            "set pose2d.import.files to the file's path relative to the recording directory"
        )
    if len(matches) > 1:
        raise ImportFormatError(
            f"{recording_dir}: {pattern!r} matches {len(matches)} files for {what} "
            f"({', '.join(m.name for m in matches[:4])}); make pose2d.import.files select one"
        )
    return matches[0]


def _closest_file(recording_dir: Path, pattern: str) -> str:
    """``"did you mean 'x'? "`` for the file in the pattern's folder most like it, else ``""``."""
    folder = (recording_dir / pattern).parent
    try:
        names = [p.relative_to(recording_dir).as_posix() for p in folder.iterdir() if p.is_file()]
    except (OSError, ValueError):
        return ""
    return did_you_mean(pattern, names)


def import_files(
    target: ImportTarget, spec: dict, recording_dir: str | Path
) -> dict[str, Path | None]:
    """The file each view's 2D is read from (``None``: mapped to nothing), without reading it;
    no match or several is an :class:`ImportFormatError`."""
    recording_dir = Path(recording_dir)
    views = target.checked_views()
    if spec["format"] == "deepfly3d":
        path = _glob_one(
            recording_dir, _df3d_pattern(spec, recording_dir), "the DeepFly3D 2D pickle"
        )
        return dict.fromkeys(views, path)
    return _view_files(spec, target, recording_dir, views)


def footage_problem(target: ImportTarget, spec: dict, recording_dir: str | Path) -> str | None:
    """Why the import would find no frame size for a view (one line), or ``None``; from file
    names alone, before the workflow builds its DAG."""
    views = target.checked_views()
    if spec["format"] == "deepfly3d":
        views = [v for v in (spec.get("views") or views) if v is not None]
    return _views.missing_footage(
        target.footage(Path(recording_dir)),
        Path(recording_dir),
        views,
        spec.get("image_size"),
        globs=target.footage_globs(),
    )


def _df3d_pattern(spec: dict, recording_dir: Path) -> str:
    """The DeepFly3D pickle pattern: ``files``, else the default in the first of
    :func:`flylib.interop.df3d.result_folders` holding one."""
    patterns = [f"{sub}df3d_result*.pkl" for sub in result_folders(recording_dir)]
    found = (p for p in patterns if list(recording_dir.glob(p)))
    return str(spec.get("files") or next(found, patterns[0]))


def _view_files(
    spec: dict, target: ImportTarget, recording_dir: Path, views: list[str]
) -> dict[str, Path | None]:
    files = spec.get("files", _DEFAULT_FILES[spec["format"]])
    if isinstance(files, dict):
        missing = [v for v in views if v not in files]
        if missing:
            raise ImportFormatError(
                f"pose2d.import.files has no file for views {missing}; add '<view>: path' "
                "entries (or '<view>: null' for a view nothing observes)"
            )
        return {
            v: None if files[v] is None else _glob_one(recording_dir, str(files[v]), f"view {v!r}")
            for v in views
        }
    placeholders = ("{view}", "{index}", "{source}", "{stem}")
    if not isinstance(files, str) or not any(k in files for k in placeholders):
        raise ImportFormatError(
            f"pose2d.import.files is {files!r}; give a pattern with a {{view}}, {{index}}, "
            "{source} or {stem} placeholder, or a mapping {view: path}"
        )
    sources = target.view_sources
    patterns = target.source_patterns
    out = {}
    for i, v in enumerate(views):
        source = sources.get(v, v)
        stem = Path(str(patterns.get(source) or source)).stem
        pattern = files.format(view=v, index=i, source=source, stem=stem)
        out[v] = _glob_one(recording_dir, pattern, f"view {v!r}")
    return out


def _point_targets(names: list, keypoint_map: dict, points: list[str], origin: str, default=None):
    """For each file keypoint, its skeleton point index or ``None`` (dropped)."""
    index = {p: i for i, p in enumerate(points)}
    lookup = {str(k): v for k, v in keypoint_map.items()}
    targets: list[int | None] = []
    seen: dict[int, str] = {}
    for name in names:
        key = str(name)
        if key in lookup:
            target = lookup[key]
        elif default is not None:
            target = default(name)
        else:
            target = key
        if target is None:
            targets.append(None)
            continue
        if target not in index:
            raise ImportFormatError(
                f"{origin}: keypoint {key!r} maps to {target!r}, which is not a skeleton point; "
                f"add it to pose2d.import.keypoint_map (a skeleton point name, or null to drop it)"
            )
        p = index[target]
        if p in seen:
            raise ImportFormatError(
                f"{origin}: keypoints {seen[p]!r} and {key!r} both map to {target!r}; "
                "fix pose2d.import.keypoint_map"
            )
        seen[p] = key
        targets.append(p)
    return targets


def _check_frames(
    counts: dict[str, int],
    footage_counts: dict[str, int | None],
    origin: dict,
    footage: dict | None = None,
) -> int:
    values = set(counts.values())
    if len(values) > 1:
        detail = ", ".join(f"{v}: {n} ({origin[v]})" for v, n in counts.items())
        raise ImportFormatError(
            f"imported views have different frame counts ({detail}); export every view "
            "from the same frames"
        )
    n_frames = values.pop()
    for view, n in footage_counts.items():
        if n is not None and view in counts and n != n_frames:
            files = (footage or {}).get(view) or []
            where = f" ({files[0]}{' ...' if len(files) > 1 else ''})" if files else ""
            raise ImportFormatError(
                f"{origin[view]}: {n_frames} frames but view {view!r} footage has {n}{where}; "
                "import the file made from this recording's footage, or re-copy truncated footage"
            )
    return n_frames


def _import_deepfly3d(spec, target: ImportTarget, recording_dir, views, points):
    path = _glob_one(recording_dir, _df3d_pattern(spec, recording_dir), "the DeepFly3D 2D pickle")
    pickle_views = spec.get("views") or views
    known = set(views)
    bad = [v for v in pickle_views if v is not None and v not in known]
    if bad:
        raise ImportFormatError(
            f"pose2d.import.views names unknown views {bad}; configured: {views}"
        )
    sized = [v for v in pickle_views if v is not None]
    footage = target.footage(recording_dir)
    sizes = _views.image_sizes(
        footage,
        recording_dir,
        sized,
        spec.get("image_size"),
        origin=str(path),
        globs=target.footage_globs(),
    )
    default_size = next(iter(sizes.values())) if sizes else (480, 960)
    data = read_df3d_points2d(path, [sizes.get(v, default_size) for v in pickle_views])
    data.conf = as_confidences(data.conf, "deepfly3d", path)
    if not np.array_equal(data.camera_ordering, np.arange(len(data.camera_ordering))):
        log.warning(
            "%s: DeepFly3D camera_ordering is %s; its rows are placed on views %s in order "
            "(set pose2d.import.views to change that)",
            path,
            data.camera_ordering.tolist(),
            pickle_views,
        )
    n_joints = data.xy.shape[2]
    keypoint_map = spec.get("keypoint_map") or {}
    default = df3d_joint_to_fly38 if n_joints == 38 else None
    unmapped = [j for j in range(n_joints) if str(j) not in {str(k) for k in keypoint_map}]
    if default is None and unmapped:
        raise ImportFormatError(
            f"{path}: 'points2d' has {n_joints} joints, but only DeepFly3D's 38 map to the "
            f"fly38 skeleton by default; set pose2d.import.keypoint_map {{joint index: skeleton "
            f"point name or null}} for joints {_ranges(unmapped)}"
        )
    targets = _point_targets(list(range(n_joints)), keypoint_map, points, str(path), default)
    n_frames = data.xy.shape[1]
    origin = dict.fromkeys(sized, path)
    _check_frames(
        dict.fromkeys(sized, n_frames),
        {v: _views.read_frame_count(footage.get(v, [])) for v in sized},
        origin,
        footage,
    )
    pts = np.full((len(views), n_frames, len(points), 2), np.nan)
    conf = np.full((len(views), n_frames, len(points)), np.nan)
    keep = [(j, p) for j, p in enumerate(targets) if p is not None]
    src_j = [j for j, _ in keep]
    dst_p = [p for _, p in keep]
    for row, view in enumerate(pickle_views):
        if view is None:
            continue
        v = views.index(view)
        pts[v][:, dst_p] = data.xy[row][:, src_j]
        conf[v][:, dst_p] = data.conf[row][:, src_j]
    return pts, conf, {v: sizes[v] for v in sized}, origin


def _warn_missing_parts(
    filled: dict[str, set[int]],
    files: dict[str, Path],
    points: list[str],
    expected: dict[str, set[int]] | None = None,
) -> None:
    """Warn, per file, about points its view should give and does not: the plan's
    ``pose2d.output_points`` for it if any (a camera sees one side of the fly), else the others'."""
    given = set().union(*filled.values()) if filled else set()
    for view, have in filled.items():
        if expected and view in expected:
            lacking, whose = (
                sorted(expected[view] - have),
                "the detection plan's pose2d.output_points give this view",
            )
        else:
            lacking = sorted(given - have) if len(filled) > 1 else []
            whose = "the other views' files have"
        if lacking:
            log.warning(
                "%s: has no columns for body parts %s that %s; "
                "they are missing in view %r (add them, or map them in pose2d.import.keypoint_map)",
                files[view],
                [points[p] for p in lacking],
                whose,
                view,
            )


def _plan_points(target: ImportTarget, points: list[str]) -> dict[str, set[int]]:
    """``view -> point indices`` the plan's ``pose2d.output_points`` assigns (may be empty)."""
    index = {name: i for i, name in enumerate(points)}
    return {
        str(view): {index[p] for p in entries if p in index}
        for view, entries in target.plan_points.items()
    }


def _keep_plan_points(
    pts: np.ndarray,
    conf: np.ndarray,
    views: list[str],
    plan: dict[str, set[int]],
    origin: dict[str, Path],
    points: list[str],
) -> None:
    """Set missing each view's 2D of the points the plan does not give it; warn once per file."""
    dropped: dict[str, list[str]] = {}  # file -> "view: n points (names)"
    for v, view in enumerate(views):
        if view not in plan:
            continue
        outside = np.ones(len(points), bool)
        outside[sorted(plan[view])] = False
        held = np.isfinite(pts[v][:, outside]).all(-1).any(axis=0)  # per dropped point
        pts[v][:, outside] = np.nan
        conf[v][:, outside] = np.nan
        if held.any():
            names = [points[p] for p in np.flatnonzero(outside)[held]]
            shown = ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
            where = str(origin.get(view, "pose2d.import"))
            dropped.setdefault(where, []).append(f"view {view!r} {len(names)} ({shown})")
    for where, views_text in dropped.items():
        log.warning(
            "%s: holds 2D for points the detection plan does not give their view: %s; they "
            "are left missing, as the detector would leave them (set "
            "pose2d.import.view_points: all to keep them)",
            where,
            "; ".join(views_text),
        )


def _check_observed(pts: np.ndarray, views: list[str], origin: dict[str, Path], threshold) -> None:
    """Refuse 2D with no observed point (no 3D can come of it); warn about views observing none."""
    cut = "" if threshold is None else f" at or above likelihood_threshold {threshold}"
    observed = np.isfinite(pts).all(-1).any(axis=(1, 2))  # (V,)
    files = list(dict.fromkeys(str(f) for f in origin.values()))
    if not observed.any():
        raise ImportFormatError(
            f"{', '.join(files) or 'pose2d.import'}: the imported 2D has no observed point{cut} in any "
            "view or frame, so there is nothing to reconstruct; check the files, "
            "pose2d.import.keypoint_map and pose2d.import.likelihood_threshold"
        )
    for v, view in enumerate(views):
        if view in origin and not observed[v]:
            log.warning(
                "%s: no observed point%s in view %r in any frame; the view contributes nothing",
                origin[view],
                cut,
                view,
            )


def _ranges(indices: list[int]) -> str:
    """``[0, 1, 2, 5]`` -> ``"0-2, 5"`` (a short list of joint indices for messages)."""
    parts, start = [], None
    for i, j in enumerate(indices):
        if start is None:
            start = j
        if i + 1 == len(indices) or indices[i + 1] != j + 1:
            parts.append(str(start) if start == j else f"{start}-{j}")
            start = None
    return ", ".join(parts)


#: Formats whose scores are probabilities: a value outside [0, 1] is not the tool's output.
_PROBABILITIES = ("dlc_csv", "dlc_h5", "deeplabcut", "lightning_pose")
#: How far rounding may take a probability past [0, 1] (clipped without a word).
_ROUNDING = 1e-6


def as_confidences(
    conf: Float[np.ndarray, "*batch K"], fmt: str, path: Path, names: list | None = None
) -> Float[np.ndarray, "*batch K"]:
    """Another tool's scores ``(..., K)`` as confidences in [0, 1] (NaN stays NaN).

    DeepLabCut / Lightning Pose likelihoods outside [0, 1] are an :class:`ImportFormatError`;
    SLEAP scores and DeepFly3D heatmap peaks may exceed 1 and are clipped with a warning."""
    conf = np.asarray(conf, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        outside = (conf < -_ROUNDING) | (conf > 1 + _ROUNDING) | np.isinf(conf)
    if not outside.any():
        return np.clip(conf, 0.0, 1.0)
    bad = conf[outside]
    where = np.argwhere(outside)[0]
    part = f", keypoint {names[where[-1]]!r}" if names is not None else ""
    detail = (
        f"{bad.size} score{'s' if bad.size > 1 else ''} outside [0, 1], from {bad.min():g} to {bad.max():g} "
        f"(first at frame {where[0] if conf.ndim == 2 else where[-2]}{part})"
    )
    if fmt in _PROBABILITIES:
        raise ImportFormatError(
            f"{path}: {detail}; a DeepLabCut / Lightning Pose likelihood is a probability in "
            "[0, 1]: check that the likelihood columns are the tool's own output"
        )
    log.warning(
        "%s: %s; %s scores are not probabilities, so they are clipped into [0, 1] as "
        "confidences (see docs/guides/imports.md)",
        path,
        detail,
        "SLEAP's point" if fmt == "sleap" else "DeepFly3D's heatmap",
    )
    return np.clip(conf, 0.0, 1.0)


def _read_view(fmt: str, path: Path, spec: dict, max_bytes: int) -> ViewKeypoints:
    """One view's file; HDF5 datasets may declare at most ``max_bytes`` (see ``read_budget``)."""
    if fmt == "dlc_h5" or (fmt == "deeplabcut" and path.suffix.lower() in (".h5", ".hdf5")):
        kp = read_dlc_h5(path, spec.get("individual"), max_bytes=max_bytes)
    elif fmt in ("dlc_csv", "lightning_pose", "deeplabcut"):
        kp = read_dlc_csv(path, spec.get("individual"))
    else:
        kp = read_sleap_analysis(path, spec.get("track"), max_bytes=max_bytes)
    kp.conf = as_confidences(kp.conf, fmt, path, kp.names)
    return kp


def _import_per_view(spec, target: ImportTarget, recording_dir, views, points):
    files = _view_files(spec, target, recording_dir, views)
    present = [v for v in views if files[v] is not None]
    origin = {v: files[v] for v in present}
    footage = target.footage(recording_dir)
    footage_counts = {v: _views.read_frame_count(footage.get(v, [])) for v in present}
    read = {
        v: _read_view(spec["format"], files[v], spec, read_budget(footage_counts[v], len(points)))
        for v in present
    }
    keypoint_map = spec.get("keypoint_map") or {}
    n_frames = (
        _check_frames({v: read[v].xy.shape[0] for v in present}, footage_counts, origin, footage)
        if present
        else 0
    )
    pts = np.full((len(views), n_frames, len(points), 2), np.nan)
    conf = np.full((len(views), n_frames, len(points)), np.nan)
    filled: dict[str, set[int]] = {}
    for view in present:
        kp = read[view]
        targets = _point_targets(kp.names, keypoint_map, points, str(kp.source))
        v = views.index(view)
        filled[view] = {p for p in targets if p is not None}
        for k, p in enumerate(targets):
            if p is not None:
                pts[v, :, p] = kp.xy[:, k]
                conf[v, :, p] = kp.conf[:, k]
    _warn_missing_parts(filled, origin, points, _plan_points(target, points))
    sizes = _views.image_sizes(
        footage,
        recording_dir,
        views,
        spec.get("image_size"),
        origin="pose2d.import",
        globs=target.footage_globs(),
    )
    return pts, conf, sizes, origin


def import_points2d(target: ImportTarget, recording_dir: Path, spec: Mapping | None):
    """Read another tool's 2D keypoints for one recording as a :class:`flylib.results.Pose2dData`:
    ``pts2d`` ``(V, T, P, 2)`` raw-frame pixels, ``conf`` ``(V, T, P)``, NaN where unobserved.

    ``spec``: the recording's import spec, else ``pose2d.import``; relative ``files`` resolve
    against ``recording_dir``. Any problem is one :class:`ImportFormatError` line naming the fix."""
    from ..results import Pose2dData

    spec = import_spec(spec)
    recording_dir = Path(recording_dir)
    views = target.checked_views()
    points = list(target.point_names)
    if spec["format"] == "deepfly3d":
        pts, conf, sizes, origin = _import_deepfly3d(spec, target, recording_dir, views, points)
    else:
        pts, conf, sizes, origin = _import_per_view(spec, target, recording_dir, views, points)
    if spec.get("view_points", "plan") == "plan":
        _keep_plan_points(pts, conf, views, _plan_points(target, points), origin, points)
    threshold = spec.get("likelihood_threshold")
    if threshold is not None:
        low = ~(conf >= float(threshold))  # NaN confidences count as below
        pts[low] = np.nan
        conf[low] = np.nan
    pts[~np.isfinite(pts).all(-1)] = np.nan
    _check_observed(pts, views, origin, threshold)
    log.info(
        "imported %s 2D for %d views x %d frames x %d points from %s",
        spec["format"],
        pts.shape[0],
        pts.shape[1],
        pts.shape[2],
        recording_dir,
    )
    return Pose2dData(pts2d=pts, conf=conf, view_names=list(views), image_sizes=sizes)
