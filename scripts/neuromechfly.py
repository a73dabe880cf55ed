#!/usr/bin/env python
"""neuromechfly stage: NeuroMechFly leg joint angles from results.h5 -> neuromechfly.h5,
joint_angles.csv (flygym's kinematic-replay layout) and joint_angles.png."""

from pathlib import Path

from _cli import add_results_argument, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.neuromechfly import run_neuromechfly

    parser = script_parser(__doc__)
    add_results_argument(parser)
    parser.add_argument("--outdir", required=True, type=Path, help="recording output directory")
    return script_main(parser, run_neuromechfly, argv, job=job, stage="neuromechfly")


if __name__ == "__main__":
    run_script(main, globals())
