#!/usr/bin/env python
"""export_nwb: one recording's results.h5 as an NWB file (ndx-pose), with the session
metadata of the config's nwb table and the recording's nwb.yaml."""

from pathlib import Path

from _cli import add_results_argument, run_script, script_main, script_parser


def main(argv=None, *, job=None) -> int:
    from flylib.pipeline.export_nwb import NwbExportInputs, run_export_nwb

    parser = script_parser(__doc__)
    add_results_argument(parser)
    parser.add_argument(
        "--recording",
        dest="recording_dir",
        required=True,
        type=Path,
        help="recording directory (footage linked from the NWB file, nwb.yaml)",
    )
    parser.add_argument(
        "--output", dest="out_path", required=True, type=Path, help="destination .nwb file"
    )
    parser.add_argument(
        "--angles",
        dest="angles_path",
        type=Path,
        help="neuromechfly.h5 of the recording: its joint angles go in the NWB file too",
    )
    parser.add_argument(
        "--demo",
        action="store_true",
        help="the recording is the embedded demo (its synthetic session metadata applies)",
    )
    return script_main(
        parser,
        run_export_nwb,
        argv,
        job=job,
        stage=NwbExportInputs,
        outdir=lambda a: a["out_path"].parent,
    )


if __name__ == "__main__":
    run_script(main, globals())
