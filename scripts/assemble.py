#!/usr/bin/env python
"""assemble: results.h5 from the stage artifacts, plus summary.json, summary.png and
calibration.toml (the final rig as an Anipose calibration)."""

import sys
from pathlib import Path

from _cli import run_script, script_main, script_parser


def run(inputs, outdir, *, recording_dir=None, **arguments) -> None:
    """``run_assemble`` with the stage artifacts (stage -> path, ``None`` for a stage
    that did not run) among ``arguments``; for the demo, print the 3D error against the
    truth."""
    from flylib.pipeline.assemble import run_assemble
    from flylib.results.artifacts import ARTIFACTS

    files = {stage: arguments.pop(stage) for stage in ARTIFACTS}
    summary = run_assemble(inputs, files, outdir, recording_dir=recording_dir, **arguments)
    where = recording_dir or outdir
    error = summary.get("error_vs_truth")
    if error:
        print(
            f"[{where}] 3D error against the demo truth: "
            f"median {error['median']:.4f}, p95 {error['p95']:.4f} world units "
            f"(body length {error['body_length']:.2f}); after similarity alignment "
            f"median {error['median_aligned']:.4f}; "
            f"{100 * error['reconstructed']:.1f}% of points reconstructed",
            file=sys.stderr,
        )
    before = summary.get("error_vs_truth_triangulation")
    if error and before:
        print(
            f"[{where}] the refined 3D above; triangulation alone: "
            f"median {before['median']:.4f}, p95 {before['p95']:.4f}, after similarity alignment "
            f"median {before['median_aligned']:.4f} ({100 * before['reconstructed']:.1f}% reconstructed)",
            file=sys.stderr,
        )


def snapshot_text(args) -> dict:
    """The snapshot's text by hand: --config's (the job's: its ``params.config_text``)."""
    from flylib.config import Config

    text = Config.from_file(args.config).snapshot_text() if args.snapshot_path else None
    return {"snapshot_text": text}


def main(argv=None, *, job=None) -> int:
    from flylib.results.artifacts import ARTIFACTS

    parser = script_parser(__doc__)
    for stage in ARTIFACTS:
        parser.add_argument(
            f"--{stage.replace('_', '-')}",
            type=Path,
            help=f"{stage} artifact (.h5), if that stage ran",
        )
    parser.add_argument("--outdir", required=True, type=Path, help="recording output directory")
    parser.add_argument("--recording", dest="recording_dir", type=Path, help="recording directory")
    parser.add_argument(
        "--truth",
        dest="truth_path",
        type=Path,
        help="demo truth.h5: report the 3D error against it",
    )
    parser.add_argument(
        "--snapshot",
        dest="snapshot_path",
        type=Path,
        help="write a byte-for-byte copy of the config here, after the results "
        "(e.g. <outdir>/config.yaml)",
    )
    return script_main(
        parser,
        run,
        argv,
        job=job,
        stage="assemble",
        job_extra=lambda job: {"snapshot_text": job.params.config_text},
        hand_extra=snapshot_text,
    )


if __name__ == "__main__":
    run_script(main, globals())
