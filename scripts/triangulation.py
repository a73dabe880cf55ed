#!/usr/bin/env python
"""triangulation stage: lift the 2D keypoints to 3D."""

from pathlib import Path

from flylib.pipeline.triangulation import run_triangulation

from _cli import add_rig_stage_arguments, output_dir, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--pose2d", required=True, type=Path, help="pose2d artifact (.h5)")
    parser.add_argument(
        "--pictorial-structures",
        type=Path,
        default=None,
        help="pictorial-structures artifact: triangulate its corrected 2D instead",
    )
    add_rig_stage_arguments(parser)
    parser.add_argument(
        "--corrections",
        type=Path,
        default=None,
        help="corrections.h5 sidecar (flylib gui): apply its manual edits",
    )

    def run(args, inputs):
        run_triangulation(
            inputs,
            args.pose2d,
            args.out,
            pictorial_path=args.pictorial_structures,
            ba_path=args.bundle_adjustment,
            recording_dir=args.recording,
            corrections_path=args.corrections,
        )

    return script_main(
        parser, run, argv, job=job, stage="triangulation", outdir=lambda args: output_dir(args.out)
    )


if __name__ == "__main__":
    run_script(main, globals())
