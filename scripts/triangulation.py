#!/usr/bin/env python
"""triangulation stage: lift the 2D keypoints to 3D."""

from pathlib import Path

from _cli import add_rig_stage_arguments, artifact_outdir, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.triangulation import run_triangulation

    parser = script_parser(__doc__)
    parser.add_argument(
        "--pose2d", dest="pose2d_path", required=True, type=Path, help="pose2d artifact (.h5)"
    )
    parser.add_argument(
        "--pictorial-structures",
        dest="pictorial_path",
        type=Path,
        help="pictorial-structures artifact: triangulate its corrected 2D instead",
    )
    add_rig_stage_arguments(parser)
    parser.add_argument(
        "--corrections",
        dest="corrections_path",
        type=Path,
        help="corrections.h5 sidecar (flylib gui): apply its manual edits",
    )
    return script_main(
        parser, run_triangulation, argv, job=job, stage="triangulation", outdir=artifact_outdir
    )


if __name__ == "__main__":
    run_script(main, globals())
