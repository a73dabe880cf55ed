#!/usr/bin/env python
"""Generate the embedded synthetic demo recording (footage, DeepLabCut CSVs, truth.h5)."""

from pathlib import Path

from _cli import run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.demo import DemoInputs, run_demo

    parser = script_parser(__doc__)
    parser.add_argument(
        "--out",
        dest="directory",
        required=True,
        type=Path,
        help="demo recording directory to write",
    )
    return script_main(parser, run_demo, argv, job=job, stage=DemoInputs)


if __name__ == "__main__":
    run_script(main, globals())
