#!/usr/bin/env python
"""bundle_adjustment stage: refine the camera rig against the recording's 2D keypoints."""

from pathlib import Path

from flylib.pipeline.bundle_adjustment import run_bundle_adjustment

from _cli import output_dir, run_script, script_main, script_parser


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

    def run(args, inputs):
        run_bundle_adjustment(inputs, args.pose2d, args.out, recording_dir=args.recording)

    return script_main(
        parser,
        run,
        argv,
        job=job,
        stage="bundle_adjustment",
        outdir=lambda args: output_dir(args.out),
    )


if __name__ == "__main__":
    run_script(main, globals())
