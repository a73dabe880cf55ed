#!/usr/bin/env python
"""refinement stage: re-solve the triangulated 3D of every frame at once (robust
reprojection, temporal smoothness, constant bone lengths, rigid tethered thorax)."""

from pathlib import Path

from flylib.pipeline.refinement import run_refinement

from _cli import (
    add_rig_stage_arguments,
    output_dir,
    path,
    rig_stage_job_arguments,
    run_script,
    script_main,
    script_parser,
)


def run(inputs, pose2d, triangulation, out, *, bundle_adjustment=None, recording=None) -> None:
    """Refine ``triangulation``'s 3D against ``pose2d`` into ``out``."""
    run_refinement(
        inputs,
        pose2d,
        triangulation,
        out,
        ba_path=bundle_adjustment,
        recording_dir=recording,
    )


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job."""
    return {
        "pose2d": path(job.input.pose2d),
        "triangulation": path(job.input.triangulation),
        **rig_stage_job_arguments(job),
    }


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument(
        "--pose2d", required=True, type=Path, help="pose2d artifact (.h5): 2D and confidences"
    )
    parser.add_argument(
        "--triangulation",
        required=True,
        type=Path,
        help="triangulation artifact (.h5): the starting 3D and its inlier views",
    )
    add_rig_stage_arguments(parser)
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        stage="refinement",
        outdir=lambda a: output_dir(a["out"]),
    )


if __name__ == "__main__":
    run_script(main, globals())
