#!/usr/bin/env python
"""pose2d stage: 2D keypoints of one recording (detector, or another tool's files)."""

import argparse
from pathlib import Path

from _cli import artifact_outdir, run_script, script_main, script_parser


def _import_spec(text: str):
    """The --import-spec JSON (the job's: ``null`` for the config's), nesting bounded
    (a ConfigError line, not a traceback)."""
    from flylib.config.loading import parse_json
    from flylib.errors import ConfigError

    try:
        return parse_json(text, "--import-spec")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.pose2d import run_pose2d

    parser = script_parser(__doc__)
    parser.add_argument(
        "--recording", dest="recording_dir", required=True, type=Path, help="recording directory"
    )
    parser.add_argument(
        "--out", dest="out_path", required=True, type=Path, help="pose2d artifact to write (.h5)"
    )
    parser.add_argument(
        "--import-spec",
        type=_import_spec,
        help="JSON pose2d.import spec for this recording (default: the config's)",
    )
    parser.add_argument(
        "--candidates-out",
        dest="candidates_path",
        type=Path,
        help="also write the detector's top-K peaks here (for pictorial structures)",
    )
    parser.add_argument("--progress", action="store_true", help="show a progress bar")
    return script_main(parser, run_pose2d, argv, job=job, stage="pose2d", outdir=artifact_outdir)


if __name__ == "__main__":
    run_script(main, globals())
