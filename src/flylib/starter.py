"""``flylib init DIR``: a starter config for a folder of recordings.

:func:`survey` finds recordings under ``DIR`` (a few levels deep): each camera's footage (videos
or image sequences), 2D files of DeepFly3D, DeepLabCut, Lightning Pose or SLEAP, and DeepFly3D /
Anipose calibrations. :func:`starter_yaml` writes them as a commented config merged over the
default, with ``undecided`` lines for what it could not decide. Files are only listed and their
headers read (pickles through flylib's safe reader, never executed)."""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import yaml

VIDEO_SUFFIXES = frozenset({".mp4", ".avi", ".mov", ".mkv", ".m4v"})
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp"})
#: How deep below DIR recordings are looked for.
MAX_DEPTH = 4
_SKIP = {"flylib_outputs", ".snakemake", "__pycache__", "labeled-data"}
_NUMBERED = re.compile(r"^(.*?)(\d+)(\D*)$")


@dataclass
class Recording:
    """One recording folder (``path``) found by :func:`survey`: ``footage``,
    ``source name -> footage glob`` in the default config's source order (empty when its cameras
    were not recognised); ``imports``, import specs (``{"format", "files"}``) of the 2D files
    found, best first; ``calibrations``, ``(format, file name)`` of calibration files found in
    the folder."""

    path: Path
    footage: dict[str, str] = field(default_factory=dict)
    imports: list[dict] = field(default_factory=list)
    calibrations: list[tuple[str, str]] = field(default_factory=list)


@dataclass
class Survey:
    """What :func:`survey` found under a folder, and what it could not decide."""

    root: Path
    recordings: list[Recording]
    sources: dict[str, str] | None
    calibration: dict | None
    undecided: list[str]
    removed: list[str] = field(default_factory=list)


def _default_sources() -> dict[str, str]:
    from .config import Config

    return Config.default().source_patterns()


def _view_sources() -> dict[str, str]:
    from .config import Config
    from .config.sources import view_sources

    return view_sources(Config.default())


def _views_of(footage: dict[str, str]) -> list[str]:
    """The default rig's cameras ``footage`` feeds (every camera when it is empty)."""
    return [v for v, s in _view_sources().items() if s in footage or not footage]


def _candidate_dirs(root: Path) -> Iterable[Path]:
    for here, dirs, _ in os.walk(root):
        depth = len(Path(here).relative_to(root).parts)
        dirs[:] = sorted(
            d for d in dirs if not d.startswith(".") and d not in _SKIP and depth < MAX_DEPTH
        )
        yield Path(here)


def _numbered_groups(names: Sequence[str], suffixes: frozenset[str]) -> dict[str, list[str]]:
    """``glob -> member names`` of numbered files with one of ``suffixes`` (``camera_0_img_12.jpg``
    joins ``camera_0_img_*.jpg``)."""
    groups: dict[str, list[str]] = {}
    for name in names:
        stem, suffix = os.path.splitext(name)
        match = _NUMBERED.match(stem)
        if suffix.lower() in suffixes and match:
            groups.setdefault(f"{match[1]}*{match[3]}{suffix}", []).append(name)
    return {g: members for g, members in groups.items() if len(members) > 1}


def _footage(folder: Path, names: list[str], defaults: dict[str, str]) -> tuple[dict, str | None]:
    """``(source -> glob, note)``: the default names that match (at least two of them), else
    videos or image sequences numbered like the cameras: as many as the default rig has, mapped to
    its sources in number order; fewer, each to the source of its number."""
    import fnmatch

    matched = {s: p for s, p in defaults.items() if fnmatch.filter(names, p)}
    if len(matched) == len(defaults):
        return matched, None
    videos = sorted(n for n in names if Path(n).suffix.lower() in VIDEO_SUFFIXES)
    sequences = sorted(_numbered_groups(names, IMAGE_SUFFIXES))
    for kind, found in (("videos", videos), ("image sequences", sequences)):
        numbers = [_NUMBERED.match(Path(f).stem.replace("*", "")) for f in found]
        if len(matched) == len(found) > 1:
            return matched, None
        if len(found) == len(defaults):
            order = sorted(
                range(len(found)),
                key=lambda i: (int(numbers[i][2]) if numbers[i] else i, found[i]),
            )
            return {s: found[i] for s, i in zip(defaults, order, strict=True)}, (
                f"{folder}: {kind} {', '.join(found[i] for i in order)} taken as cameras "
                f"{', '.join(defaults)} in that order; check the order"
            )
        taken = sorted({int(m[2]) for m in numbers if m})
        if 1 < len(found) == len(taken) and taken[-1] < len(defaults):
            sources = list(defaults)
            by_number = {sources[int(m[2])]: f for m, f in zip(numbers, found, strict=True)}
            mapping = {s: by_number[s] for s in sources if s in by_number}
            return mapping, (
                f"{folder}: {kind} {', '.join(mapping.values())} taken as cameras "
                f"{', '.join(mapping)} by their numbers; check the order"
            )
    if videos or sequences:
        return {}, (
            f"{folder}: {len(videos)} video(s) and {len(sequences)} image sequence(s), not the "
            f"{len(defaults)} cameras of the default rig; list them in `sources` and describe "
            "the rig in `cameras` (or a `calibration` file)"
        )
    return {}, None


def _per_view_pattern(
    files: Sequence[str], views: Sequence[str], stems: Sequence[str]
) -> str | None:
    """The ``files`` pattern naming one file per view (``{index}``, ``{view}`` or ``{stem}`` in
    place of what differs between them), or ``None``."""
    if len(files) != len(views):
        return None
    prefix = os.path.commonprefix(list(files))
    suffix = os.path.commonprefix([f[::-1] for f in files])[::-1]
    shortest = min(map(len, files))
    while len(prefix) + len(suffix) > shortest:
        suffix = suffix[1:]
    middles = [f[len(prefix) : len(f) - len(suffix)] for f in files]
    # a common prefix may have taken the start of the stems or of the view names
    for placeholder, names in (
        ("{index}", [str(i) for i in range(len(views))]),
        ("{view}", list(views)),
        ("{stem}", list(stems)),
    ):
        for cut in range(len(prefix) + 1):
            head, tail = prefix[:cut], prefix[cut:]
            if sorted(tail + m for m in middles) == sorted(names):
                return f"{head}{placeholder}{suffix}"
    return None


def _dlc_like(path: Path) -> str | None:
    """``dlc_csv`` or ``lightning_pose`` for a DeepLabCut-style CSV (scorer/bodyparts/coords header
    rows), else ``None``."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            head = [f.readline() for _ in range(3)]
    except OSError:
        return None
    if not (head[0].startswith("scorer") and "bodyparts" in head[1] and "coords" in head[2]):
        return None
    return "lightning_pose" if "heatmap" in head[0] else "dlc_csv"


def _imports(folder: Path, names: list[str], footage: dict[str, str]) -> list[dict]:
    views = _views_of(footage)
    stems = [Path(p).stem for p in footage.values()] if footage else []
    found = [{"format": "deepfly3d", "files": f} for f in _df3d_2d(folder)]
    per_view: dict[str, list[str]] = {
        fmt: [] for fmt in ("sleap", "dlc_h5", "dlc_csv", "lightning_pose")
    }
    for name in names:
        lower = name.lower()
        if lower.endswith(".analysis.h5"):
            per_view["sleap"].append(name)
        elif lower.endswith(".h5") and "dlc" in lower:
            per_view["dlc_h5"].append(name)
        elif lower.endswith(".csv"):
            fmt = _dlc_like(folder / name)
            if fmt:
                per_view[fmt].append(name)
    for fmt, files in per_view.items():
        pattern = _per_view_pattern(sorted(files), views, stems) if files else None
        if pattern:
            found.append({"format": fmt, "files": pattern})
    return found


def _df3d_2d(folder: Path) -> list[str]:
    """The DeepFly3D pickles holding 2D in ``folder``'s result folders, newest first."""
    from .errors import FlylibError
    from .interop.df3d import load_pickle, result_folders

    found = []
    for order, sub in enumerate(result_folders(folder)):
        for pkl in sorted((folder / sub).glob("df3d_result*.pkl")):
            try:
                if "points2d" in load_pickle(pkl, "DeepFly3D result"):
                    found.append((-pkl.stat().st_mtime, order, f"{sub}{pkl.name}"))
            except (FlylibError, OSError, ValueError):
                continue
    return [name for *_, name in sorted(found)]


def _calibrations(folder: Path, names: list[str], results: bool = False) -> list[tuple[str, str]]:
    from .errors import FlylibError
    from .interop.anipose import read_anipose_toml
    from .interop.df3d import read_df3d_calibration

    found = []
    for name in names:
        lower = name.lower()
        if lower.endswith(".pkl") and (results or not lower.startswith("df3d_result")):
            reader, fmt = read_df3d_calibration, "deepfly3d"
        elif lower.endswith(".toml"):
            reader, fmt = read_anipose_toml, "anipose"
        else:
            continue
        try:
            reader(folder / name)
        except (FlylibError, OSError, ValueError):
            continue
        found.append((fmt, name))
    return found


def survey(root: str | Path) -> Survey:
    """Find the recordings under ``root`` and what each holds (module docstring)."""
    root = Path(root).expanduser().absolute()
    defaults = _default_sources()
    recordings: list[Recording] = []
    undecided: list[str] = []
    top_calibrations = _calibrations(root, sorted(p.name for p in root.iterdir() if p.is_file()))
    inside: list[Path] = []
    for folder in _candidate_dirs(root):
        if any(folder.is_relative_to(r) and folder != r for r in inside) or (
            folder.name.endswith("_df3d") and folder.with_name(folder.name[:-5]).is_dir()
        ):
            continue  # inside a recording, or DeepFly3D's results of the one beside it
        names = sorted(p.name for p in folder.iterdir() if p.is_file())
        footage, note = _footage(folder, names, defaults)
        imports = _imports(folder, names, footage)
        if note:
            undecided.append(note)
        if not footage and not imports:
            continue
        inside.append(folder)
        calibrations = _calibrations(folder, names) if folder != root else top_calibrations
        if imports and imports[0]["format"] == "deepfly3d":  # a 1.x result holds its calibration
            calibrations = [*calibrations, *_calibrations(folder, [imports[0]["files"]], True)]
        recordings.append(Recording(folder, footage, imports, calibrations))
    sources = _common_sources(recordings, defaults, undecided)
    view_sources, kept = (
        _view_sources(),
        _views_of(next((r.footage for r in recordings if r.footage), {})),
    )
    removed = [v for v in view_sources if v not in kept]
    if removed:
        unused = ", ".join(defaults[view_sources[v]] for v in removed)
        undecided.append(
            f"the default rig's camera(s) {', '.join(removed)} have no footage ({unused}): "
            f"removed (cameras: {_flow(dict.fromkeys(removed))}); check that your rig has none there"
        )
    calibration = _common_calibration(root, recordings, top_calibrations, undecided)
    for rec in recordings:  # each has footage or 2D files
        first = rec.imports[0]["files"] if rec.imports else ""
        if len(rec.imports) > 1:
            df3d = all(i["format"] == "deepfly3d" for i in rec.imports)
            undecided.append(
                f"{rec.path}: {len(rec.imports)} {'DeepFly3D pickles with 2D' if df3d else '2D files of several tools'} "
                f"({', '.join(i['files'] for i in rec.imports)}); using "
                f"{'the newest, ' if df3d else ''}{first}; set pose2d.import.files to take another"
            )

        if not rec.footage:
            undecided.append(
                f"{rec.path}: no footage: set pose2d.import.image_size: [height, width] "
                "(the cameras' frame size in pixels)"
            )
    if not recordings:
        undecided.append(
            f"{root}: no recording found (a folder with {', '.join(defaults.values())}, "
            "or with 2D files of DeepFly3D, DeepLabCut, Lightning Pose or SLEAP)"
        )
    return Survey(root, recordings, sources, calibration, undecided, removed)


def _common_sources(recordings, defaults, undecided) -> dict[str, str] | None:
    """The ``sources`` entry to write: ``None`` when the (first) recording uses default names."""
    seen = {tuple(r.footage.items()) for r in recordings if r.footage}
    if len(seen) > 1:
        undecided.append(
            "recordings name their camera files (or have cameras) differently; `sources` (one "
            "list for all) follows the first; run such recordings with a config each"
        )
    first = next((r.footage for r in recordings if r.footage), {})
    return dict(first) if set(first.items()) - set(defaults.items()) else None


def _common_calibration(root, recordings, top, undecided) -> dict | None:
    per_recording = {tuple(r.calibrations) for r in recordings if r.path != root}
    if top:
        if len(top) > 1:
            undecided.append(
                f"{root}: several calibration files {[n for _, n in top]}; using {top[0][1]}"
            )
        fmt, name = top[0]
        return _handed(
            {"file": str(root / name), "format": fmt}, recordings[0] if recordings else None
        )
    if len(per_recording) == 1 and next(iter(per_recording)):
        found = next(iter(per_recording))
        if len(found) > 1:
            undecided.append(
                f"several calibration files {[n for _, n in found]}; using {found[0][1]}"
            )
        fmt, name = found[0]
        # a relative file resolves against each recording's folder
        return _handed({"file": name, "format": fmt}, recordings[0])
    having = [r.path.name for r in recordings if r.calibrations]
    if len(per_recording) > 1 and len(having) < len(recordings):
        undecided.append(
            f"only {', '.join(having)} hold(s) a calibration file: run them with a config of "
            "their own, or add `calibration: {file: NAME}` when every recording shares that rig"
        )
    elif len(per_recording) > 1:
        undecided.append(
            "recordings hold different calibration files; give each recording's rig with "
            "`calibration: {index: calibrations.csv}` (see the imports guide)"
        )
    return None


def _handed(calibration: dict, rec: Recording | None) -> dict:
    """``calibration`` with ``mirror: true`` and ``why`` when it is DeepFly3D's and mirrors the
    default rig (:func:`flylib.pipeline.preflight.calibration_handedness`)."""
    from .config import Config
    from .pipeline.preflight import calibration_handedness

    config = Config.from_dict({**Config.default().data, "calibration": calibration})
    verdict = calibration_handedness(config, rec.path if rec else None)
    if verdict is not None and verdict.mirrored:
        return {**calibration, "mirror": True, "why": verdict.reason}
    return calibration


def _writable(path: Path) -> bool:
    return os.access(path, os.W_OK | os.X_OK)


def _flow(value) -> str:
    """``value`` as one line of YAML (a flow mapping or list, or a quoted-if-needed scalar)."""
    text = yaml.safe_dump([value], default_flow_style=True, sort_keys=False, width=10_000)
    return text.strip()[1:-1]


def starter_yaml(found: Survey, where: Path, outdir: str | None = None) -> str:
    """The starter config's text for ``found``: outputs go to ``outdir`` (a path template) when
    given, else beside each recording, or under ``where`` (the folder the config is written to)
    when a recording's folder cannot be written."""
    lines = [
        f"# flylib config for the recordings in {found.root}, written by `flylib init`.",
        "# It is merged over the workflow's config/config.yaml (the default rig and skeleton).",
        "# Check it, then dry-run and run:",
        "#   flylib check-config THIS_FILE",
        "#   snakemake -n --configfile THIS_FILE && snakemake --cores 2 --configfile THIS_FILE",
        "",
        "recordings:",
    ]
    firsts = [r.imports[0] if r.imports else None for r in found.recordings]
    shared_import = (
        firsts[0] if firsts and firsts[0] and all(f == firsts[0] for f in firsts) else None
    )
    for rec in found.recordings:
        what = []
        if rec.footage:
            globs = list(rec.footage.values())
            what.append(f"footage {globs[0]} .. {globs[-1]} ({len(globs)} cameras)")
        if rec.imports:
            what.append(f"2D {rec.imports[0]['files']} ({rec.imports[0]['format']})")
        entry: str | dict = str(rec.path)
        if rec.imports and shared_import is None:
            entry = {"path": str(rec.path), "import": rec.imports[0]}
        lines.append(f"  - {_flow(entry)}   # {'; '.join(what)}")
    if not found.recordings:
        lines[-1] = "recordings: []   # none found: list recording folders here"
    if outdir is not None:
        lines += [
            "",
            "# Where outputs go ({id}: each recording's name)",
            f"outdir: {_flow(outdir)}",
        ]
    elif any(not _writable(r.path) for r in found.recordings):
        lines += [
            "",
            "# The recordings' folders cannot be written here: outputs go beside this file.",
            f"outdir: {_flow(str(where.absolute() / 'flylib_outputs' / '{id}'))}",
        ]
    if found.removed:
        lines += [
            "",
            "# The default rig's cameras without footage here, removed with their detection plan:",
            f"cameras: {_flow(dict.fromkeys(found.removed))}",
        ]
    if found.sources:
        lines += ["", "# Each camera's footage, in the rig's camera order (check it):", "sources:"]
        lines += [f"  - {_flow({'name': n, 'filename': f})}" for n, f in found.sources.items()]
    if shared_import is not None:
        lines += [
            "",
            "# 2D from another tool instead of the detector (no weights needed):",
            "pose2d:",
            "  import:",
        ]
        lines += [f"    {key}: {_flow(value)}" for key, value in shared_import.items()]
        if not any(r.footage for r in found.recordings):
            lines.append(
                "    # image_size: [height, width]   # needed without footage: the frame size in pixels"
            )
    elif not any(r.imports for r in found.recordings):
        lines += [
            "",
            "# No 2D files found: the detector runs (`flylib doctor` says where its weights go).",
        ]
    if found.calibration:
        calibration = dict(found.calibration)
        why = calibration.pop("why", None)
        lines += ["", "# The rig from a calibration file (bundle adjustment still refines it):"]
        if why:
            lines.append(f"# mirror: its world is the fly's mirror image ({why}); mirrored back")
        lines.append(f"calibration: {_flow(calibration)}")
    return "\n".join(lines) + "\n"
