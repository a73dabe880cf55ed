#!/usr/bin/env python
"""pictorial_structures stage: recover joints from the detector's candidate peaks."""

from pathlib import Path

from flylib.pipeline.pictorial_structures import run_pictorial_structures

from _cli import add_rig_stage_arguments, output_dir, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--pose2d", required=True, type=Path, help="pose2d artifact")
    parser.add_argument(
        "--candidates",
        type=Path,
        default=None,
        help="the detector's top-K peaks (default: those inside the pose2d artifact)",
    )
    add_rig_stage_arguments(parser)

    def run(args, inputs):
        run_pictorial_structures(
            inputs,
            args.pose2d,
            args.out,
            candidates_path=args.candidates,
            ba_path=args.bundle_adjustment,
            recording_dir=args.recording,
        )

    return script_main(
        parser,
        run,
        argv,
        job=job,
        stage="pictorial_structures",
        outdir=lambda args: output_dir(args.out),
    )


if __name__ == "__main__":
    run_script(main, globals())
