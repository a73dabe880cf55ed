#!/usr/bin/env python
"""assemble: results.h5 from the stage artifacts, plus summary.json, summary.png and
calibration.toml (the final rig as an Anipose calibration)."""

import sys
from pathlib import Path

from flylib.pipeline.artifacts import ARTIFACTS
from flylib.pipeline.assemble import run_assemble

from _cli import run_script, script_main, script_parser


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

    def snapshot_text(args) -> str | None:
        """The run's config text: the rule's ``params.config_text``, or --config's."""
        if args.snapshot is None:
            return None
        if job is not None:
            return job.params.config_text
        from flylib.config import Config

        return Config.from_file(args.config).snapshot_text()

    def run(args, inputs):
        files = {stage: getattr(args, stage) for stage in ARTIFACTS}
        summary = run_assemble(
            inputs,
            files,
            args.outdir,
            recording_dir=args.recording,
            truth_path=args.truth,
            snapshot_path=args.snapshot,
            snapshot_text=snapshot_text(args),
        )
        error = summary.get("error_vs_truth")
        if error:
            print(
                f"[{args.recording or args.outdir}] 3D error against the demo truth: "
                f"median {error['median']:.4f}, p95 {error['p95']:.4f} world units "
                f"(body length {error['body_length']:.2f}); after similarity alignment "
                f"median {error['median_aligned']:.4f}; "
                f"{100 * error['reconstructed']:.1f}% of points reconstructed",
                file=sys.stderr,
            )
        before = summary.get("error_vs_truth_triangulation")
        if error and before:
            print(
                f"[{args.recording or args.outdir}] the refined 3D above; triangulation alone: "
                f"median {before['median']:.4f}, p95 {before['p95']:.4f}, after similarity alignment "
                f"median {before['median_aligned']:.4f} ({100 * before['reconstructed']:.1f}% reconstructed)",
                file=sys.stderr,
            )

    return script_main(
        parser, run, argv, job=job, stage="assemble", outdir=lambda args: args.outdir
    )


if __name__ == "__main__":
    run_script(main, globals())
