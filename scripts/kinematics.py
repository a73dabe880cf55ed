#!/usr/bin/env python
"""kinematics stage: body frame and joint angles from results.h5 -> kinematics.h5,
angles.csv (Anipose's angles layout) and angles.png (angle traces per leg)."""

import sys
from pathlib import Path

import _bootstrap  # noqa: F401

from flylib.stages import run_kinematics, script_main, script_parser


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--results", required=True, type=Path, help="results.h5 of the recording")
    parser.add_argument("--outdir", required=True, type=Path, help="recording output directory")

    def run(args, config):
        run_kinematics(config, args.results, args.outdir)

    return script_main(parser, run, argv, outdir=lambda args: args.outdir)


if __name__ == "__main__":
    sys.exit(main())
