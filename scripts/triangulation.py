#!/usr/bin/env python
"""triangulation stage: lift the 2D keypoints to 3D."""

from pathlib import Path

from flylib.pipeline.triangulation import run_triangulation

from _cli import (
    add_rig_stage_arguments,
    output_dir,
    path,
    rig_stage_job_arguments,
    run_script,
    script_main,
    script_parser,
)


def run(
    inputs,
    pose2d,
    out,
    *,
    pictorial_structures=None,
    bundle_adjustment=None,
    recording=None,
    corrections=None,
) -> None:
    """Triangulate ``pose2d`` (or the pictorial-structures 2D) into ``out``."""
    run_triangulation(
        inputs,
        pose2d,
        out,
        pictorial_path=pictorial_structures,
        ba_path=bundle_adjustment,
        recording_dir=recording,
        corrections_path=corrections,
    )


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job."""
    return {
        "pose2d": path(job.input.pose2d),
        "pictorial_structures": path(job.input.get("pictorial_structures")),
        "corrections": path(job.input.get("corrections")),
        **rig_stage_job_arguments(job),
    }


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
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        stage="triangulation",
        outdir=lambda a: output_dir(a["out"]),
    )


if __name__ == "__main__":
    run_script(main, globals())
