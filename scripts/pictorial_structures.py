#!/usr/bin/env python
"""pictorial_structures stage: recover joints from the detector's candidate peaks."""

from pathlib import Path

from flylib.pipeline.pictorial_structures import run_pictorial_structures

from _cli import (
    add_rig_stage_arguments,
    output_dir,
    path,
    rig_stage_job_arguments,
    run_script,
    script_main,
    script_parser,
)


def run(inputs, pose2d, out, *, candidates=None, bundle_adjustment=None, recording=None) -> None:
    """Recover the joints of ``pose2d`` from the candidate peaks into ``out``."""
    run_pictorial_structures(
        inputs,
        pose2d,
        out,
        candidates_path=candidates,
        ba_path=bundle_adjustment,
        recording_dir=recording,
    )


def job_arguments(job) -> dict:
    """``run``'s arguments from the Snakemake job."""
    return {
        "pose2d": path(job.input.pose2d),
        "candidates": path(job.input.get("candidates")),
        **rig_stage_job_arguments(job),
    }


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
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=job_arguments,
        stage="pictorial_structures",
        outdir=lambda a: output_dir(a["out"]),
    )


if __name__ == "__main__":
    run_script(main, globals())
