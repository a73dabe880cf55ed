#!/usr/bin/env python
"""bundle_adjustment stage: refine the camera rig against the recording's 2D keypoints."""

from pathlib import Path

from flylib.pipeline.bundle_adjustment import run_bundle_adjustment

from _cli import output_dir, path, run_script, script_main, script_parser


def run(inputs, pose2d, out, *, recording=None) -> None:
    """Bundle-adjust the rig on ``pose2d`` into ``out``."""
    run_bundle_adjustment(inputs, pose2d, out, recording_dir=recording)


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job."""
    return {
        "pose2d": path(job.input.pose2d),
        "out": path(job.output[0]),
        "recording": path(job.params.recording),
    }


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--pose2d", required=True, type=Path, help="pose2d artifact (.h5)")
    parser.add_argument(
        "--out", required=True, type=Path, help="bundle-adjustment artifact to write"
    )
    parser.add_argument(
        "--recording",
        type=Path,
        default=None,
        help="recording directory (resolves a per-session calibration file)",
    )
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        stage="bundle_adjustment",
        outdir=lambda a: output_dir(a["out"]),
    )


if __name__ == "__main__":
    run_script(main, globals())
