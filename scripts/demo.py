#!/usr/bin/env python
"""Generate the embedded synthetic demo recording (footage, DeepLabCut CSVs, truth.h5)."""

import sys
from pathlib import Path

import _bootstrap  # noqa: F401

from flylib.stages import run_demo, script_main, script_parser


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--out", required=True, type=Path, help="demo recording directory to write")
    return script_main(parser, lambda args, config: run_demo(config, args.out), argv)


if __name__ == "__main__":
    sys.exit(main())
