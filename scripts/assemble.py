#!/usr/bin/env python
"""assemble: results.h5 from the stage artifacts, plus summary.json, summary.png and
calibration.toml (the final rig as an Anipose calibration)."""

import sys
from pathlib import Path

from flylib.pipeline.artifacts import ARTIFACTS
from flylib.pipeline.assemble import run_assemble

from _cli import path, run_script, script_main, script_parser


def run(
    inputs, files, outdir, *, recording=None, truth=None, snapshot=None, snapshot_text=None
) -> None:
    """Assemble the stage artifacts ``files`` (stage -> path, ``None`` for a stage that
    did not run) into ``outdir``; for the demo, print the 3D error against ``truth``."""
    summary = run_assemble(
        inputs,
        files,
        outdir,
        recording_dir=recording,
        truth_path=truth,
        snapshot_path=snapshot,
        snapshot_text=snapshot_text,
    )
    error = summary.get("error_vs_truth")
    if error:
        print(
            f"[{recording or outdir}] 3D error against the demo truth: "
            f"median {error['median']:.4f}, p95 {error['p95']:.4f} world units "
            f"(body length {error['body_length']:.2f}); after similarity alignment "
            f"median {error['median_aligned']:.4f}; "
            f"{100 * error['reconstructed']:.1f}% of points reconstructed",
            file=sys.stderr,
        )
    before = summary.get("error_vs_truth_triangulation")
    if error and before:
        print(
            f"[{recording or outdir}] the refined 3D above; triangulation alone: "
            f"median {before['median']:.4f}, p95 {before['p95']:.4f}, after similarity alignment "
            f"median {before['median_aligned']:.4f} ({100 * before['reconstructed']:.1f}% reconstructed)",
            file=sys.stderr,
        )


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job (the snapshot's text: the rule's
    ``params.config_text``)."""
    return {
        "files": {stage: path(job.input.get(stage)) for stage in ARTIFACTS},
        "outdir": path(job.wildcards.outdir),
        "recording": path(job.params.recording),
        "truth": path(job.input.get("truth")),
        "snapshot": path(job.output.snapshot),
        "snapshot_text": job.params.config_text,
    }


def hand_arguments(args) -> dict:
    """``run``'s arguments by hand (the snapshot's text: --config's)."""
    snapshot_text = None
    if args.snapshot is not None:
        from flylib.config import Config

        snapshot_text = Config.from_file(args.config).snapshot_text()
    return {
        "files": {stage: getattr(args, stage) for stage in ARTIFACTS},
        "outdir": args.outdir,
        "recording": args.recording,
        "truth": args.truth,
        "snapshot": args.snapshot,
        "snapshot_text": snapshot_text,
    }


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    for stage in ARTIFACTS:
        parser.add_argument(
            f"--{stage.replace('_', '-')}",
            type=Path,
            default=None,
            help=f"{stage} artifact (.h5), if that stage ran",
        )
    parser.add_argument("--outdir", required=True, type=Path, help="recording output directory")
    parser.add_argument("--recording", type=Path, default=None, help="recording directory")
    parser.add_argument(
        "--truth", type=Path, default=None, help="demo truth.h5: report the 3D error against it"
    )
    parser.add_argument(
        "--snapshot",
        type=Path,
        default=None,
        help="write a byte-for-byte copy of the config here, after the results "
        "(e.g. <outdir>/config.yaml)",
    )
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        hand_arguments=hand_arguments,
        stage="assemble",
        outdir=lambda a: a["outdir"],
    )


if __name__ == "__main__":
    run_script(main, globals())
