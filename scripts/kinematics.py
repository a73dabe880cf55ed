#!/usr/bin/env python
"""kinematics stage: body frame and joint angles from results.h5 -> kinematics.h5,
angles.csv (Anipose's angles layout) and angles.png (angle traces per leg)."""

from pathlib import Path

from _cli import add_results_argument, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.kinematics import run_kinematics

    parser = script_parser(__doc__)
    add_results_argument(parser)
    parser.add_argument("--outdir", required=True, type=Path, help="recording output directory")
    return script_main(parser, run_kinematics, argv, job=job, stage="kinematics")


if __name__ == "__main__":
    run_script(main, globals())
