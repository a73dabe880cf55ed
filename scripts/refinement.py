#!/usr/bin/env python
"""refinement stage: re-solve the triangulated 3D of every frame at once (robust
reprojection, temporal smoothness, constant bone lengths, rigid tethered thorax)."""

from pathlib import Path

from _cli import add_rig_stage_arguments, artifact_outdir, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.refinement import run_refinement

    parser = script_parser(__doc__)
    parser.add_argument(
        "--pose2d",
        dest="pose2d_path",
        required=True,
        type=Path,
        help="pose2d artifact (.h5): 2D and confidences",
    )
    parser.add_argument(
        "--triangulation",
        dest="triangulation_path",
        required=True,
        type=Path,
        help="triangulation artifact (.h5): the starting 3D and its inlier views",
    )
    add_rig_stage_arguments(parser)
    return script_main(
        parser, run_refinement, argv, job=job, stage="refinement", outdir=artifact_outdir
    )


if __name__ == "__main__":
    run_script(main, globals())
