#!/usr/bin/env python
"""session_calibration: one bundle adjustment over frames sampled from every recording
of a session (one rig); writes the session's rig (.h5 artifact and calibration.toml)."""

import json
from pathlib import Path

from _cli import add_session_arguments, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.session_calibration import (
        SessionCalibrationInputs,
        run_session_calibration,
    )

    parser = script_parser(__doc__)
    add_session_arguments(parser)
    parser.add_argument(
        "--recordings",
        dest="recording_dirs",
        nargs="*",
        type=Path,
        help="the members' recording directories (a per-recording calibration file)",
    )
    parser.add_argument(
        "--out", dest="out_path", required=True, type=Path, help="session artifact to write"
    )
    parser.add_argument(
        "--calibration",
        dest="calibration_path",
        required=True,
        type=Path,
        help="the session's calibration.toml to write (Anipose format)",
    )
    return script_main(
        parser,
        run_session_calibration,
        argv,
        job=job,
        stage=SessionCalibrationInputs,
        outdir=lambda a: a["out_path"].parent,
        job_extra=lambda job: {
            "pose2d_paths": [Path(p) for p in job.input.pose2d_files],
            "members": json.loads(job.params.members),
            "recording_dirs": [Path(p) for p in json.loads(job.params.recordings)],
        },
    )


if __name__ == "__main__":
    run_script(main, globals())
