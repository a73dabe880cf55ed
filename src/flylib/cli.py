"""The ``flylib`` console script: look at, export and reuse a run's ``results.h5``.

A user-facing error is one line on stderr and exit status 1. ``inspect`` first checks every
dataset against its checksum (a damaged file: one line per damaged dataset, status 1), then
compares the params hashes each stage recorded with the config snapshot beside the file (or
``--config``): a stale or mixed file prints one line per problem after the tables, status 2."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import numpy as np

from .errors import ConfigError, FlylibError, ResultsError
from .results import PoseResult, open_checked, summarize_results

# -- printing ---------------------------------------------------------------------


#: Columns holding fractions, printed as percentages like the end-of-run table.
_PERCENT_COLUMNS = frozenset({"observed_2d", "reconstructed"})


def _cell(value, percent: bool = False) -> str:
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            return "-"
        if percent:
            return f"{100 * float(value):.1f}%"
        return f"{value:.3g}" if abs(value) >= 1e-3 or value == 0 else f"{value:.2e}"
    return "-" if value is None else str(value)


def _print_table(title: str, rows: list[dict], columns: list[tuple[str, str]]) -> None:
    """Print rows as an aligned plain-text table (first column left, the rest right)."""
    cells = [[_cell(r.get(key), key in _PERCENT_COLUMNS) for key, _ in columns] for r in rows]
    widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, (_, h) in enumerate(columns)]

    def line(values) -> str:
        return "  ".join(
            v.ljust(w) if i == 0 else v.rjust(w) for i, (v, w) in enumerate(zip(values, widths))
        )

    print(title)
    print(line([h for _, h in columns]))
    for c in cells:
        print(line(c))
    print()


def _verify(args) -> int:
    """``inspect --verify``: one line per failed invariant of :mod:`flylib.results.invariants`
    and per artifact made with other settings than the config (status 1), or one saying
    they hold (status 0)."""
    from .pipeline.planning import params_of
    from .provenance import stale_artifacts
    from .results.invariants import check_results, describe

    path = args.results
    found = check_results(path)
    config, config_path = _compared_config(args)
    stale = stale_artifacts(path, params_of(config, run_only=True), config_path) if config else []
    if not found and not stale:
        print(
            f"{path}: consistent (stored reprojection errors match the stored 2D, 3D and "
            "cameras; the 2D is what the 3D was solved from, corrections applied; the "
            "flags match the NaN patterns"
            + (f"; every artifact made with {config_path}'s settings)" if config else ")")
        )
        return 0
    views, points = describe(path)
    for line in [f"{path}: {v.line(views, points)}" for v in found] + stale:
        print(f"flylib inspect: {line}", file=sys.stderr)
    return 1


def _cmd_inspect(args) -> int:
    from .results import verify_file

    unchecked: list[str] = []
    damaged = verify_file(args.results, unchecked=unchecked) if args.results.is_file() else []
    if damaged:
        for line in damaged:
            print(f"flylib inspect: {line}", file=sys.stderr)
        return 1
    if unchecked:
        print(
            f"flylib inspect: note: {args.results}: {len(unchecked)} datasets carry no checksum "
            f"(e.g. {unchecked[0]}; written by an older flylib), so their integrity cannot be "
            "verified; re-run the workflow to regenerate the file",
            file=sys.stderr,
        )
    if args.verify:
        return _verify(args)
    summary = summarize_results(args.results)
    meta = summary["meta"]
    print(
        f"{args.results}  (format version {meta.get('deeperfly_format_version', '?')}, "
        f"created {meta.get('created_utc', '?')})"
    )
    _print_table(
        "stages",
        summary["stages"],
        [
            ("stage", "stage"),
            ("views", "views"),
            ("frames", "frames"),
            ("observed_2d", "2D observed"),
            ("reconstructed", "3D reconstructed"),
            ("err_median", "err median px"),
            ("err_p95", "err p95 px"),
            ("held_median", "held-out median px"),
            ("held_p95", "held-out p95 px"),
            ("cameras", "cameras"),
        ],
    )
    session = summary["session"]
    if session:  # as the run's session line names the rig the results use
        folder = session["folder"]
        where = f": {Path(folder) / 'calibration.toml'}" if folder else ""
        print(
            f"rig: session {session['name']}'s, solved over {', '.join(session['members'])}{where}\n"
        )
    _print_handedness(summary["handedness"])
    if summary["accuracy"] is not None:
        from .run_summary import HELD_OUT_NOTE, accuracy_line

        print(f"accuracy: {HELD_OUT_NOTE}")
        line = accuracy_line(
            str(args.results), summary["accuracy"] | {"output_stage": summary["stage_3d"]}
        )
        if line:
            print(f"  {line}")
        print()
    _print_table(
        f"points ({summary['stage_3d'] or 'no 3D stage'})",
        summary["points"],
        [
            ("point", "point"),
            ("views_observing", "views/frame"),
            ("reconstructed", "reconstructed"),
            ("err_median", "err median px"),
            ("err_p95", "err p95 px"),
            ("held_median", "held-out median px"),
            ("held_p95", "held-out p95 px"),
        ],
    )
    if summary["bones"]:
        _print_table(
            "bones",
            summary["bones"],
            [
                ("bone", "bone"),
                ("frames", "frames"),
                ("median_length", "median length"),
                ("spread", "IQR / median"),
            ],
        )
    if summary["stage_3d"]:
        _print_suspects(args.results)
    return _print_provenance(args)


def _print_handedness(entry: dict | None) -> None:
    """Whether the 3D is a fly or its mirror image (:mod:`flylib.handedness`); if mirrored, why
    and the fix."""
    if not entry:
        return
    print(f"handedness: {entry['verdict']}: {entry['reason']}")
    start = entry.get("starting_rig")
    if start:
        print(f"  starting rig ({entry.get('rig')}): {start['verdict']}: {start['reason']}")
    if entry.get("message"):
        print(f"  MIRROR IMAGE: {entry['message']}")
    print()


def _compared_config(args):
    """The config ``inspect`` compares params hashes with and its name: ``--config``'s, else
    the snapshot beside the file (``None`` without either)."""
    from .config import Config
    from .provenance import snapshot_beside

    if args.config:  # the user's files, merged over the default config as the workflow does
        from .config.layers import ConfigLayers
        from .paths import DEFAULT_CONFIG_PATH

        layers = ConfigLayers.from_files([DEFAULT_CONFIG_PATH, *args.config])
        return Config.from_dict(layers.data), " + ".join(map(str, args.config))
    config_path = snapshot_beside(args.results)
    return (Config.from_file(config_path) if config_path else None), config_path


def _print_provenance(args) -> int:
    """The provenance table; status 2 when the file is stale or mixes runs."""
    from .pipeline.planning import params_of
    from .provenance import provenance_report

    config, config_path = _compared_config(args)

    rows = provenance_report(args.results, params_of(config) if config is not None else None)
    _print_table(
        f"provenance (params hashes; compared with {config_path or 'no config: pass --config'})",
        [
            {"stage": r.stage, "recorded": r.recorded, "expected": r.expected, "status": r.status}
            for r in rows
        ],
        [
            ("stage", "stage"),
            ("recorded", "recorded"),
            ("expected", "config gives"),
            ("status", "status"),
        ],
    )
    problems = [line for r in rows for line in r.problems]
    for line in problems:
        print(f"flylib inspect: {line}", file=sys.stderr)
    return 2 if problems else 0


def _print_suspects(path: Path) -> None:
    from collections import Counter

    from .suspects import suspects_from_results

    try:
        suspects = suspects_from_results(path)
    except ResultsError as exc:  # e.g. 3D without reprojection errors: nothing to judge
        print(f"suspects: not computed ({exc})")
        return
    reasons = Counter(r for rs in suspects.reasons for r in rs.split(";"))
    detail = ", ".join(f"{name} {n}" for name, n in reasons.most_common())
    print(
        f"suspects: {len(suspects)} (frame, point) pairs in {len(suspects.frames)} frames"
        + (
            f", {suspects.n_items} items (a point's consecutive frames, best first in "
            f"suspects.csv) ({detail}); review them with `flylib gui {path}`"
            if len(suspects)
            else ""
        )
    )


def _export_inputs(args) -> dict[str, str]:
    """``file -> role`` of what ``flylib export`` reads: no output may land on one."""
    inputs = {str(args.results): "the input RESULTS_H5"}
    beside = args.results.parent
    for name in ("config.yaml", "config.toml"):
        inputs[str(beside / name)] = "the config snapshot beside RESULTS_H5"
    inputs[str(beside / "corrections.h5")] = "the corrections beside RESULTS_H5"
    if args.config is not None:
        inputs[str(args.config)] = "the --config file"
    if args.nwb_metadata is not None:
        inputs[str(args.nwb_metadata)] = "the --nwb-metadata file"
    return inputs


def _cmd_export(args) -> int:
    from .interop.exports import export_result
    from .paths import refuse_overwrite

    if {args.csv3d, args.dlc_dir, args.nwb, args.training_data} == {None}:
        raise FlylibError(
            "export: nothing to do; pass --csv3d FILE, --dlc-dir DIR, --nwb FILE "
            "and/or --training-data DIR"
        )
    result = PoseResult.load(args.results)
    # every file this export writes, checked before any is written
    targets = {args.csv3d: "--csv3d", args.nwb: "--nwb"}
    if args.dlc_dir is not None:
        targets |= {args.dlc_dir / f"{view}.csv": "--dlc-dir" for view in result.cameras.names}
    targets.pop(None, None)
    inputs = _export_inputs(args)
    for target, option in targets.items():
        refuse_overwrite(target, inputs, f"flylib export {option}", force=args.force)
    if args.training_data is not None:
        from .config import Config
        from .config.sources import footage_globs
        from .interop.training_data import export_training_data
        from .interop.views import footage_files

        config = Config.from_file(args.config) if args.config else None

        def footage_of(recording: Path) -> dict[str, list[Path]]:
            # the run's config: --config, else the snapshot beside results.h5, else the default
            run = config if config is not None else Config.of_outputs(Path(args.results).parent)
            return footage_files(footage_globs(run), recording)

        written = export_training_data(
            args.results,
            args.training_data,
            footage_of=footage_of,
            recording=args.recording,
            scorer=args.scorer,
            protected=inputs,
            report=print,
        )
        labels = sorted({p.parent for p in written})
        print(f"{len(written)} files in {len(labels)} labeled-data folders:")
        for folder in labels:
            print(folder)
    if args.nwb is not None:
        from .pipeline.export_nwb import export_nwb_command

        path = export_nwb_command(
            args.results,
            args.nwb,
            config_path=args.config,
            recording=args.recording,
            metadata_path=args.nwb_metadata,
        )
        _recorded(path)
    if args.csv3d is not None or args.dlc_dir is not None:
        detections = None
        if args.dlc_dir is not None:
            from .results import read_detections

            detections = read_detections(args.results)
            print(
                f"--dlc-dir: pose2d's detections, {detections.corrected} observations "
                "corrected by hand (corrections.h5) applied",
                file=sys.stderr,
            )
        for path in export_result(
            result, csv3d=args.csv3d, dlc_dir=args.dlc_dir, detections=detections
        ):
            _recorded(path)
    return 0


def _cmd_calibration(args) -> int:
    from .interop.anipose import write_anipose_toml
    from .paths import refuse_overwrite

    refuse_overwrite(
        args.output,
        {str(args.results): "the input RESULTS_H5"},
        "flylib calibration -o",
        force=args.force,
    )
    result = PoseResult.load(args.results)
    with open_checked(args.results) as f:
        stage = "bundle_adjustment" if "bundle_adjustment/cameras" in f else "pose2d"
    path = write_anipose_toml(
        result.cameras,
        args.output,
        result.image_sizes or {},
        metadata={"source": str(args.results), "rig": stage},
    )
    _recorded(path)
    return 0


def _recorded(path) -> None:
    """Record ``path`` as flylib's (:func:`~flylib.paths.record_outputs`), print it."""
    from .paths import record_outputs

    record_outputs(Path(path).parent, [Path(path).name])
    print(path)


def _plain_yaml(data: dict, label: str, header: str) -> str:
    """A parsed config as plain YAML text (no tags, no templating), checked to read back as the
    same values with flylib's parser."""
    import yaml

    from .config.canonical import plain
    from .config.layers import refuse_templating
    from .config.loading import parse_text

    refuse_templating(data, label)
    try:
        body = yaml.safe_dump(plain(data), sort_keys=False, allow_unicode=True)
    except yaml.YAMLError as err:
        raise ConfigError(f"{label}: a value has no YAML form ({err}); write it in YAML") from None
    text = f"# {header}\n" + body
    if parse_text(text, "yaml", label) != plain(data):
        raise ConfigError(f"{label}: its values do not survive a YAML round trip; write it in YAML")
    return text


def _toml_hint(configfiles: list[Path]) -> str | None:
    """The line telling a user that ``snakemake --configfile`` cannot read their TOML."""
    tomls = [f for f in configfiles if f.suffix.lower() == ".toml"]
    if not tomls:
        return None
    files = " ".join(map(str, configfiles))
    return (
        f"{tomls[0]}: TOML, which `snakemake --configfile` cannot read (it stops with "
        '"Config file is not valid JSON or YAML"); run it with '
        f"`flylib run {' '.join(map(str, tomls))} [snakemake args]`, or write its YAML "
        f"equivalent with `flylib check-config {files} --to-yaml {tomls[0].with_suffix('.yaml')}`"
    )


def _cmd_check_config(args) -> int:
    from .bundle_adjustment.messages import rig_report
    from .config.layers import ConfigLayers
    from .pipeline.planning import RunPlan
    from .pipeline.pose2d import Pose2dInputs
    from .pipeline.preflight import load_run_config

    base = _default_base(args.configfiles, args.replace_workflow_config)
    layers = ConfigLayers.from_files([*base, *args.configfiles])
    plan = RunPlan(*load_run_config(layers), main_process=False)  # as the workflow plans
    recordings = plan.recordings
    if args.to_yaml is not None:
        tomls = [f for f in args.configfiles if f.suffix.lower() == ".toml"]
        if len(tomls) != 1:
            raise ConfigError(
                f"--to-yaml: converts one TOML config file, got {len(tomls)} among "
                f"{', '.join(map(str, args.configfiles))}"
            )
        _write_new(
            args.to_yaml,
            _plain_yaml(
                dict(layers.layers[len(base) + args.configfiles.index(tomls[0])][1]),
                str(tomls[0]),
                f"{tomls[0]} as YAML, written by flylib check-config --to-yaml",
            ),
        )
        print(f"{tomls[0]}: valid; written as YAML to {args.to_yaml}")
        return 0
    over = " over the default config" if base else ""
    print(
        f"{' + '.join(map(str, args.configfiles))}{over}: valid; {len(recordings)} recording(s): "
        + ", ".join(f"{r.id} -> {r.outdir}" for r in recordings)
        + "".join(f"; session {s.name} ({', '.join(s.ids)}) -> {s.outdir}" for s in plan.sessions)
    )
    rig = Pose2dInputs.from_config(plan.config).detection_plan()
    specs = [r.import_spec for r in recordings if r.import_spec]  # a demo's 2D is imported too
    every = all(s.get("view_points") == "all" for s in specs)
    tables = plan.config.data["pose2d"].get("output_points") or {}
    imported = len(specs) == len(recordings) > 0
    whole = [v for v in rig.view_names if imported and (every or not tables.get(v))]
    print("\n".join(rig_report(rig, plan.config.skeleton(), whole)))
    hint = _toml_hint(args.configfiles)
    if hint:
        print(hint, file=sys.stderr)
    return 0


def _default_base(configfiles: list[Path], replace: bool) -> list[Path]:
    """The default config when the workflow would merge the user's files over it: always, as the
    Snakefile's ``configfile:`` does, unless ``--replace-workflow-config`` or the first file given
    is the default config itself (its checkout copy included)."""
    from .config.constants import DEFAULT_CONFIG_PATH

    if replace:
        return []
    try:
        if configfiles[0].read_bytes() == Path(DEFAULT_CONFIG_PATH).read_bytes():
            return []
    except OSError:
        pass  # a missing file is named by the reader
    return [Path(DEFAULT_CONFIG_PATH)]


def _write_new(path: Path, text: str) -> None:
    """Write ``text`` to ``path``, which must not exist (a user's file is never replaced)."""
    from .paths import cannot_write

    try:
        with open(path, "x", encoding="utf-8") as f:
            f.write(text)
    except FileExistsError:
        raise ConfigError(f"{path}: already exists; choose another name or delete it") from None
    except OSError as err:
        raise cannot_write(path, err) from None


#: Where ``flylib run`` keeps the checked plain copies it hands to Snakemake (under the directory
#: it is run from), named by content so a copy never changes under a run.
RUN_CONFIGS = Path(".flylib") / "run-configs"


def _cmd_run(args) -> int:
    """Validate config files with flylib's safe reader, then run Snakemake on checked plain YAML
    copies of them: no config file is ever rendered by Snakemake (YTE)."""
    import hashlib
    import shutil

    from .config.constants import DEFAULT_CONFIG_PATH
    from .config.layers import ConfigLayers
    from .paths import atomic_path
    from .pipeline.preflight import load_run_config

    argv = list(args.argv)
    split = next((i for i, a in enumerate(argv) if a.startswith("-")), len(argv))
    configfiles, rest = [Path(a) for a in argv[:split]], argv[split:]
    if rest[:1] == ["--"]:
        rest = rest[1:]
    if not configfiles:
        raise ConfigError(
            "name the config file(s) first: flylib run my.yaml [snakemake args], "
            "e.g. flylib run my.yaml -n"
        )
    given = [a for a in rest if a.split("=", 1)[0] in ("--configfile", "--configfiles")]
    if given:
        raise ConfigError(
            f"{given[0]} would hand Snakemake a file flylib did not check; list every "
            "config file before the snakemake arguments: flylib run a.yaml b.yaml [snakemake args]"
        )
    replace = "--replace-workflow-config" in rest
    base = [] if replace else [DEFAULT_CONFIG_PATH]
    layers = ConfigLayers.from_files([*base, *configfiles])
    load_run_config(layers)
    copies = []
    for label, data in layers.layers[len(base) :]:
        text = _plain_yaml(
            data,
            label,
            f"{label} as checked plain YAML for flylib run (edit {label}, not this copy)",
        )
        digest = hashlib.sha256(text.encode()).hexdigest()[:12]
        copy = (RUN_CONFIGS / f"{Path(label).stem}-{digest}.yaml").absolute()
        if not copy.exists():
            with atomic_path(copy) as tmp:
                tmp.write_text(text, encoding="utf-8")
        copies.append(str(copy))
    beside = Path(sys.executable).with_name("snakemake")
    snakemake = str(beside) if beside.exists() else shutil.which("snakemake")
    if snakemake is None:
        raise ConfigError("snakemake is not installed in this environment")
    command = [snakemake, "--configfile", *copies, *rest]
    print(
        f"flylib run: {' + '.join(map(str, configfiles))} checked; snakemake reads "
        + ", ".join(os.path.relpath(c) for c in copies),
        file=sys.stderr,
        flush=True,
    )
    sys.stdout.flush()
    os.execv(snakemake, command)
    return 0  # pragma: no cover (execv does not return)


def build_parser() -> argparse.ArgumentParser:
    """The ``flylib`` argument parser, one subcommand per command."""
    parser = argparse.ArgumentParser(prog="flylib", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser(
        "inspect", help="integrity, per-stage and per-point summary and provenance of a results.h5"
    )
    p.add_argument("results", type=Path, metavar="RESULTS_H5")
    p.add_argument(
        "--config",
        type=Path,
        nargs="+",
        metavar="CONFIG",
        help="config file(s) to compare the recorded params hashes with, merged in order "
        "over the default config as `snakemake --configfile` merges them (default: the "
        "config.yaml snapshot beside RESULTS_H5)",
    )
    p.add_argument(
        "--verify",
        action="store_true",
        help="only check that the result agrees with itself (reprojection errors, the 2D "
        "the 3D was solved from, flags) and that it and the stage artifacts beside it were "
        "made with the compared config's settings; one line per failed invariant naming the "
        "dataset and its worst (view, frame, point), 0-based, and per artifact of other "
        "settings; exit status 1 when one fails",
    )
    p.set_defaults(func=_cmd_inspect)

    p = sub.add_parser(
        "export", help="3D as Anipose CSV, 2D as per-view DeepLabCut CSVs, all as NWB"
    )
    p.add_argument("results", type=Path, metavar="RESULTS_H5")
    p.add_argument("--csv3d", type=Path, help="write the 3D points to this CSV")
    p.add_argument(
        "--dlc-dir",
        type=Path,
        help="write <view>.csv DeepLabCut files here: pose2d's 2D detections (as detected "
        "or imported) with the manual corrections applied, not the 2D a 3D stage kept",
    )
    p.add_argument("--nwb", type=Path, help="write an NWB file (ndx-pose) here")
    p.add_argument(
        "--training-data",
        type=Path,
        metavar="DIR",
        help="write the corrected frames as DeepLabCut labeled data (DIR/labeled-data/...)",
    )
    p.add_argument(
        "--scorer",
        default="flylib",
        help="training data: DeepLabCut's scorer name (CollectedData_<scorer>; default flylib)",
    )
    p.add_argument(
        "--config",
        type=Path,
        help="NWB, training data: the run's config (default: the config.yaml snapshot "
        "beside RESULTS_H5)",
    )
    p.add_argument(
        "--recording",
        type=Path,
        help="NWB, training data: the recording directory (footage, nwb.yaml; default: the "
        "one results.h5 names)",
    )
    p.add_argument(
        "--nwb-metadata",
        type=Path,
        help="NWB: a YAML file of session metadata overriding the config's nwb table and nwb.yaml",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace existing files flylib did not write (never one of the export's inputs)",
    )
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser(
        "check-config", help="check config files as `snakemake` would, naming file, line and key"
    )
    p.add_argument(
        "configfiles",
        type=Path,
        nargs="+",
        metavar="CONFIG",
        help="config files in the order snakemake merges them, over the default config as "
        "the workflow does, e.g. my.yaml",
    )
    p.add_argument(
        "--replace-workflow-config",
        action="store_true",
        help="the files are the whole config, not merged over the default (as snakemake's "
        "option of that name)",
    )
    p.add_argument(
        "--to-yaml",
        type=Path,
        metavar="OUT",
        help="write the one TOML config file given as plain YAML to OUT (a new file), "
        "for snakemake --configfile",
    )
    p.set_defaults(func=_cmd_check_config)

    p = sub.add_parser(
        "run",
        help="check config files with flylib's safe reader, then run snakemake on checked "
        "plain copies (a config file is never rendered as a template)",
    )
    p.add_argument(
        "argv",
        nargs=argparse.REMAINDER,
        metavar="CONFIG... [SNAKEMAKE_ARGS]",
        help="config files in merge order, then snakemake's own arguments, e.g. "
        "flylib run my.yaml -n --cores 4",
    )
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("calibration", help="write the run's camera rig as an Anipose TOML")
    p.add_argument("results", type=Path, metavar="RESULTS_H5")
    p.add_argument("-o", "--output", type=Path, required=True, help="destination .toml")
    p.add_argument(
        "--force", action="store_true", help="replace an existing file flylib did not write"
    )
    p.set_defaults(func=_cmd_calibration)

    p = sub.add_parser("gui", help="review and correct a recording's 3D pose in the browser")
    p.add_argument(
        "results",
        type=Path,
        metavar="OUTDIR_OR_RESULTS_H5",
        help="a recording's output directory or its results.h5",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; any other needs the printed token URL)",
    )
    p.add_argument(
        "--port", type=int, default=8765, help="port (default 8765; a busy one is replaced)"
    )
    p.add_argument("--no-browser", action="store_true", help="only print the URL")
    p.add_argument(
        "--footage-dir",
        type=Path,
        metavar="DIR",
        help="the folder holding the recording's videos (default: the recording "
        "directory the result names)",
    )
    p.set_defaults(func=_cmd_gui)

    what = (
        "the installation in one screen: versions, torch device, detector weights, "
        "caches, SLURM, Chromium; exit 1 when something blocks a run"
    )
    p = sub.add_parser("doctor", help=what, description=what)
    p.add_argument(
        "--config",
        type=Path,
        nargs="+",
        metavar="CONFIG",
        help="check the detector weights of these config files' models (merged over the default)",
    )
    p.set_defaults(func=_cmd_doctor)

    what = (
        "write a starter config for a folder of recordings (footage, 2D files and "
        "calibrations it finds), and say what it could not decide"
    )
    p = sub.add_parser("init", help=what, description=what)
    p.add_argument("folder", type=Path, metavar="DIR", help="the folder holding the recordings")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        default=Path("my.yaml"),
        help="the config file to write (a new file; default my.yaml)",
    )
    p.add_argument(
        "--outdir",
        metavar="TEMPLATE",
        help="where outputs go, e.g. results/{id} (default: <recording>/flylib_outputs)",
    )
    p.set_defaults(func=_cmd_init)
    return parser


def _cmd_doctor(args) -> int:
    from .doctor import FAIL, format_report, run_checks

    lines = run_checks(args.config or ())
    print(format_report(lines))
    return 1 if any(c.status == FAIL for c in lines) else 0


def _cmd_init(args) -> int:
    from .config.constants import DEFAULT_CONFIG_PATH
    from .config.layers import ConfigLayers
    from .pipeline.preflight import load_run_config
    from .starter import starter_yaml, survey

    if not args.folder.is_dir():
        raise ConfigError(f"{args.folder}: not a folder; name the folder holding your recordings")
    found = survey(args.folder)
    _write_new(args.output, starter_yaml(found, args.output.parent, args.outdir))
    print(
        f"flylib init: {len(found.recordings)} recording(s) under {found.root}; wrote {args.output}"
    )
    for line in found.undecided:
        print(f"  undecided: {line}")
    try:
        load_run_config(
            ConfigLayers.from_files([DEFAULT_CONFIG_PATH, args.output]), check_frames=False
        )
    except ConfigError as exc:
        print(f"{args.output} needs editing before a run:\n{exc}")
        return 1
    run = f"{_snakemake_here(DEFAULT_CONFIG_PATH.parents[2] / 'Snakefile')} --configfile {args.output}"
    print(f"{args.output} is valid. Next: {run} -n (a dry run), then {run} --cores 2")
    return 0


def _snakemake_here(snakefile: Path) -> str:
    """Snakemake as typed here: the one beside this Python (``.venv/bin/snakemake`` after
    install.sh, bare when it is the one on PATH), with the checkout's Snakefile unless here."""
    import shutil

    exe = Path(sys.executable).with_name("snakemake")
    on_path = shutil.which("snakemake")
    cmd = os.path.relpath(exe) if exe.is_relative_to(Path.cwd()) else str(exe)
    if not exe.exists() or on_path and Path(on_path).resolve() == exe.resolve():
        cmd = "snakemake"
    here = Path("Snakefile").resolve() == snakefile.resolve()
    return cmd if here or not snakefile.is_file() else f"{cmd} -s {snakefile}"


def _cmd_gui(args) -> int:
    from .gui.server import serve

    serve(
        args.results,
        host=args.host,
        port=args.port,
        open_browser=not args.no_browser,
        footage_dir=args.footage_dir,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``flylib`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s"
    )
    try:
        status = args.func(args)
        sys.stdout.flush()
        return status
    except FlylibError as exc:
        print(f"flylib {args.command}: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # The reader went away (`flylib inspect ... | head`): stop quietly, as Unix tools do, with
        # the status a shell reports for SIGPIPE; stdout is pointed at devnull so the
        # interpreter's final flush does not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + 13
    except OSError as exc:  # a file no writer or reader above named: still one line
        if exc.filename is None:
            raise
        print(f"flylib {args.command}: {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
