#!/usr/bin/env python
"""visualization stage: render the configured videos of one recording."""

from pathlib import Path

from _cli import add_results_argument, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.visualization import run_visualization

    parser = script_parser(__doc__)
    add_results_argument(parser)
    parser.add_argument(
        "--recording",
        dest="recording_dir",
        required=True,
        type=Path,
        help="recording directory (footage)",
    )
    parser.add_argument("--outdir", required=True, type=Path, help="where the videos go")
    parser.add_argument("--progress", action="store_true", help="show a progress bar")
    parser.add_argument(
        "--speed",
        type=float,
        help="play the videos at this multiple of the recording's rate when the config sets none",
    )
    return script_main(parser, run_visualization, argv, job=job, stage="visualization")


if __name__ == "__main__":
    run_script(main, globals())
