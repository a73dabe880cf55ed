"""The ``flylib`` console script: look at, export and reuse a run's ``results.h5``.

    flylib inspect RESULTS_H5                 per-stage and per-point summary
    flylib export RESULTS_H5 --csv3d out.csv --dlc-dir DIR
    flylib calibration RESULTS_H5 -o rig.toml  the run's (bundle-adjusted) rig as Anipose TOML

A user-facing error is printed as one line on stderr and the exit status is 1.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from .errors import FlylibError, ResultsError
from .results import open_checked

_STAGES_2D = ("pose2d", "pictorial_structures", "triangulation", "refinement")
_STAGES_3D = ("pictorial_structures", "triangulation", "refinement")


# -- reading results.h5 (schema v2, seed 004) -------------------------------------


def _decode(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel()]


def _percentile(values: np.ndarray, q: float) -> float:
    finite = values[np.isfinite(values)]
    return float(np.percentile(finite, q)) if finite.size else float("nan")


def summarize_results(path: Path) -> dict:
    """Per-stage and per-point figures of a ``results.h5`` (what ``inspect`` prints).

    Returns
    -------
    dict
        ``{"meta", "stages": [row...], "points": [row...], "bones": [row...],
        "stage_3d"}``; rows are dicts of plain numbers and strings. Reprojection
        errors are in pixels; the bone spread is the interquartile range of the
        bone's length over frames divided by its median (0 for a rigid bone).
    """
    with open_checked(path, "pass the results.h5 a run wrote") as f:
        meta = json.loads(f.attrs["meta"]) if "meta" in f.attrs else {}
        if "skeleton/point_names" not in f:
            raise ResultsError(f"{path}: no skeleton/point_names; not a flylib results file")
        names = _decode(f["skeleton/point_names"][()])
        bones = np.zeros((0, 2), int)
        if "skeleton/bones" in f:
            bones = np.asarray(f["skeleton/bones"][()], dtype=int).reshape(-1, 2)
        stages = []
        for stage in ("pose2d", "bundle_adjustment", *_STAGES_3D):
            if stage not in f:
                continue
            row: dict = {"stage": stage}
            group = f[stage]
            if "points" in group:
                pts2d = group["points"][()]
                row["views"], row["frames"] = int(pts2d.shape[0]), int(pts2d.shape[1])
                row["observed_2d"] = float(np.isfinite(pts2d).all(-1).mean())
            if "points3d" in group:
                pts3d = group["points3d"][()]
                row["frames"] = int(pts3d.shape[0])
                row["reconstructed"] = float(np.isfinite(pts3d).all(-1).mean())
            if "reproj_error" in group:
                err = group["reproj_error"][()]
                row["err_median"], row["err_p95"] = _percentile(err, 50), _percentile(err, 95)
            if "cameras/names" in group:
                row["cameras"] = len(_decode(group["cameras/names"][()]))
            stages.append(row)
        stage_3d = next((s for s in reversed(_STAGES_3D) if f"{s}/points3d" in f), None)
        source_2d = next((s for s in reversed(_STAGES_2D) if f"{s}/points" in f), None)
        pts2d = f[f"{source_2d}/points"][()] if source_2d else None
        pts3d = f[f"{stage_3d}/points3d"][()] if stage_3d else None
        err = f[f"{stage_3d}/reproj_error"][()] if stage_3d and f"{stage_3d}/reproj_error" in f else None

    points = []
    for p, name in enumerate(names):
        row = {"point": name}
        if pts2d is not None:
            row["views_observing"] = float(np.isfinite(pts2d[:, :, p]).all(-1).sum(0).mean())
        if pts3d is not None:
            row["reconstructed"] = float(np.isfinite(pts3d[:, p]).all(-1).mean())
        if err is not None:
            row["err_median"], row["err_p95"] = _percentile(err[:, :, p], 50), _percentile(err[:, :, p], 95)
        points.append(row)
    bone_rows = []
    if pts3d is not None:
        for a, b in bones:
            length = np.linalg.norm(pts3d[:, a] - pts3d[:, b], axis=-1)
            median = _percentile(length, 50)
            iqr = _percentile(length, 75) - _percentile(length, 25)
            spread = iqr / median if median > 0 else float("nan")
            bone_rows.append({
                "bone": f"{names[a]}-{names[b]}",
                "frames": int(np.isfinite(length).sum()),
                "median_length": median,
                "spread": spread,
            })
    return {"meta": meta, "stages": stages, "points": points, "bones": bone_rows, "stage_3d": stage_3d}


# -- printing ---------------------------------------------------------------------


def _cell(value) -> str:
    if isinstance(value, float):
        if not np.isfinite(value):
            return "-"
        return f"{value:.3g}" if abs(value) >= 1e-3 or value == 0 else f"{value:.2e}"
    return "-" if value is None else str(value)


def _print_table(title: str, rows: list[dict], columns: list[tuple[str, str]]) -> None:
    """Print rows as a table: ``rich`` when installed, else aligned plain text."""
    cells = [[_cell(r.get(key)) for key, _ in columns] for r in rows]
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:
        widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, (_, h) in enumerate(columns)]
        print(title)
        print("  ".join(h.ljust(w) for (_, h), w in zip(columns, widths)))
        for c in cells:
            print("  ".join(v.ljust(w) for v, w in zip(c, widths)))
        print()
        return
    table = Table(title=title, title_justify="left")
    for i, (_, header) in enumerate(columns):
        table.add_column(header, justify="left" if i == 0 else "right", no_wrap=True)
    for c in cells:
        table.add_row(*c)
    console = Console(width=None if sys.stdout.isatty() else 200)
    console.print(table)


def _cmd_inspect(args) -> int:
    summary = summarize_results(args.results)
    meta = summary["meta"]
    print(f"{args.results}  (format version {meta.get('deeperfly_format_version', '?')}, "
          f"created {meta.get('created_utc', '?')})")
    _print_table(
        "stages",
        summary["stages"],
        [("stage", "stage"), ("views", "views"), ("frames", "frames"), ("observed_2d", "2D observed"),
         ("reconstructed", "3D reconstructed"), ("err_median", "err median px"), ("err_p95", "err p95 px"),
         ("cameras", "cameras")],
    )
    _print_table(
        f"points ({summary['stage_3d'] or 'no 3D stage'})",
        summary["points"],
        [("point", "point"), ("views_observing", "views/frame"), ("reconstructed", "reconstructed"),
         ("err_median", "err median px"), ("err_p95", "err p95 px")],
    )
    if summary["bones"]:
        _print_table(
            "bones",
            summary["bones"],
            [("bone", "bone"), ("frames", "frames"), ("median_length", "median length"),
             ("spread", "IQR / median")],
        )
    return 0


def _load_result(path: Path):
    from .results import PoseResult

    return PoseResult.load(path)


def _cmd_export(args) -> int:
    from .interop.exports import export_result

    if args.csv3d is None and args.dlc_dir is None:
        raise FlylibError("export: nothing to do; pass --csv3d FILE and/or --dlc-dir DIR")
    for path in export_result(_load_result(args.results), csv3d=args.csv3d, dlc_dir=args.dlc_dir):
        print(path)
    return 0


def _cmd_calibration(args) -> int:
    from .interop.anipose import write_anipose_toml

    result = _load_result(args.results)
    with open_checked(args.results) as f:
        stage = "bundle_adjustment" if "bundle_adjustment/cameras" in f else "pose2d"
    path = write_anipose_toml(
        result.cameras, args.output, result.image_sizes or {},
        metadata={"source": str(args.results), "rig": stage},
    )
    print(path)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``flylib`` argument parser (subcommands ``inspect``, ``export``, ``calibration``)."""
    parser = argparse.ArgumentParser(prog="flylib", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("inspect", help="per-stage and per-point summary of a results.h5")
    p.add_argument("results", type=Path, metavar="RESULTS_H5")
    p.set_defaults(func=_cmd_inspect)

    p = sub.add_parser("export", help="3D as tidy CSV, 2D as per-view DeepLabCut CSVs")
    p.add_argument("results", type=Path, metavar="RESULTS_H5")
    p.add_argument("--csv3d", type=Path, help="write the 3D points to this CSV")
    p.add_argument("--dlc-dir", type=Path, help="write <view>.csv DeepLabCut files here")
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser("calibration", help="write the run's camera rig as an Anipose TOML")
    p.add_argument("results", type=Path, metavar="RESULTS_H5")
    p.add_argument("-o", "--output", type=Path, required=True, help="destination .toml")
    p.set_defaults(func=_cmd_calibration)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``flylib`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    try:
        return args.func(args)
    except FlylibError as exc:
        print(f"flylib {args.command}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
