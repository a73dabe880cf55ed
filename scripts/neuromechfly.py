#!/usr/bin/env python
"""neuromechfly stage: NeuroMechFly leg joint angles from results.h5 -> neuromechfly.h5,
joint_angles.csv (flygym's kinematic-replay layout) and joint_angles.png."""

from pathlib import Path

from flylib.pipeline.neuromechfly import run_neuromechfly

from _cli import path, run_script, script_main, script_parser


def run(inputs, results, outdir) -> None:
    """The NeuroMechFly joint angles of ``results`` into ``outdir``."""
    run_neuromechfly(inputs, results, outdir)


def main(argv=None, *, job=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--results", required=True, type=Path, help="results.h5 of the recording")
    parser.add_argument("--outdir", required=True, type=Path, help="recording output directory")
    return script_main(
        parser,
        run,
        argv,
        job=job,
        job_arguments=lambda job: {
            "results": path(job.input.results),
            "outdir": path(job.wildcards.outdir),
        },
        stage="neuromechfly",
        outdir=lambda a: a["outdir"],
    )


if __name__ == "__main__":
    run_script(main, globals())
