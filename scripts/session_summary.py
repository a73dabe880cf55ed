#!/usr/bin/env python
"""session_summary: the held-out-view error of each recording of a session with its own
rig and with the session's rig, side by side (session_summary.json)."""

import json
from pathlib import Path

from _cli import add_session_arguments, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.session_calibration import SessionSummaryInputs, run_session_summary

    parser = script_parser(__doc__)
    parser.add_argument(
        "--session",
        dest="session_path",
        required=True,
        type=Path,
        help="the session's artifact (session_calibration.h5)",
    )
    add_session_arguments(parser)
    parser.add_argument(
        "--bundle-adjustment",
        dest="trial_paths",
        nargs="+",
        required=True,
        type=Path,
        help="the members' own bundle-adjustment artifacts, in --members order",
    )
    parser.add_argument(
        "--out", dest="out_path", required=True, type=Path, help="session_summary.json to write"
    )
    return script_main(
        parser,
        run_session_summary,
        argv,
        job=job,
        stage=SessionSummaryInputs,
        outdir=lambda a: a["out_path"].parent,
        job_extra=lambda job: {
            "pose2d_paths": [Path(p) for p in job.input.pose2d_files],
            "trial_paths": [Path(p) for p in job.input.trial_files],
            "members": json.loads(job.params.members),
        },
    )


if __name__ == "__main__":
    run_script(main, globals())
