# exports: extra per-recording outputs switched on in the config's `exports` table.
#
#   exports: {nwb: true}   ->  {outdir}/results.nwb: the result as NWB (ndx-pose), with
#                              the session metadata of the `nwb` table and the recording's
#                              nwb.yaml (see flylib.interop.nwb_metadata)
#
# The rule's params are the `exports` and `nwb` tables, its inputs results.h5, the
# footage it links and the recording's nwb.yaml, so it re-runs only when one of those
# changes. Missing session metadata is one error naming every recording and key, raised
# here, before any job starts.

from flylib.interop.nwb_metadata import SIDECAR as NWB_SIDECAR
from flylib.interop.nwb_metadata import recording_metadata as _nwb_metadata
from flylib.io import VIDEO_EXTS as _VIDEO_EXTS

EXPORTS = CONFIG.data.get("exports") or {}
NWB_FILE = "results.nwb"


def _check_nwb_metadata() -> None:
    problems = []
    for rec in RECORDINGS:
        if rec.id in SKIPPED:
            continue
        try:
            metadata = _nwb_metadata(CONFIG, rec.path, demo=rec.demo)
        except FlylibError as exc:
            problems.append(str(exc))
            continue
        stills = [f for f in rec.footage if Path(f).suffix.lower() not in _VIDEO_EXTS]
        if stills and not metadata.get("frame_rate"):
            problems.append(
                f"nwb.frame_rate: recording {rec.path} is image sequences, which carry no frame rate; "
                f"set nwb.frame_rate (frames per second) in the config or in {rec.path / NWB_SIDECAR}"
            )
    if problems:
        raise WorkflowError("exports.nwb is on, but:\n  " + "\n  ".join(problems))


def export_targets() -> list[str]:
    """The export files of every recording the workflow runs (rule `all`)."""
    if not EXPORTS.get("nwb"):
        return []
    return [f"{rec.outdir}/{NWB_FILE}" for rec in RECORDINGS if rec.id not in SKIPPED]


def nwb_sidecar(wildcards) -> list[str]:
    """The recording's nwb.yaml when it has one (the demo's comes with its own data)."""
    rec = recording(wildcards)
    path = rec.path / NWB_SIDECAR
    return [str(path)] if not rec.demo and path.is_file() else []


if EXPORTS.get("nwb"):
    _check_nwb_metadata()

    rule export_nwb:
        input:
            results="{outdir}/results.h5",
            footage=footage_inputs,
            metadata=nwb_sidecar,
        output:
            f"{{outdir}}/{NWB_FILE}",
        params:
            run=command("export_nwb.py"),
            stage=json.dumps(
                {"exports": EXPORTS, "nwb": CONFIG.data.get("nwb")}, sort_keys=True, default=str
            ),
            recording=lambda w: str(recording(w).path),
            demo=lambda w: "--demo" if recording(w).demo else "",
        log:
            "{outdir}/logs/export_nwb.log",
        benchmark:
            "{outdir}/benchmarks/export_nwb.tsv"
        resources:
            mem_mb=2000,
            runtime=15,
        conda:
            "../../envs/exports.yaml"
        shell:
            "{params.run} --results {input.results:q} --recording {params.recording:q}"
            " {params.demo} --output {output:q} 2> {log:q}"
