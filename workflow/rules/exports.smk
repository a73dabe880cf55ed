# exports: extra per-recording outputs switched on in the config's `exports` table.
#
#   exports: {nwb: true}   ->  {outdir}/results.nwb: the result as NWB (ndx-pose), with
#                              the session metadata of the `nwb` table and the recording's
#                              nwb.yaml (see flylib.config.nwb_metadata)
#
# The rule's params are the `exports` and `nwb` tables, its inputs results.h5, the
# footage it links and the recording's nwb.yaml, so it re-runs only when one of those
# changes. Missing session metadata is one error naming every recording and key, raised
# here, before any job starts.

from flylib.config.nwb_metadata import recordings_metadata_problems, sidecar_inputs
from flylib.pipeline.export_nwb import NwbExportInputs
from flylib.pipeline.user_files import NWB_FILE

EXPORTS = CONFIG.data.get("exports") or {}
EXPORT_RECORDINGS = [rec for rec in RECORDINGS if rec.id not in SKIPPED]
EXPORT_TARGETS = (
    [f"{rec.outdir}/{NWB_FILE}" for rec in EXPORT_RECORDINGS] if EXPORTS.get("nwb") else []
)

if EXPORTS.get("nwb"):
    _nwb_problems = recordings_metadata_problems(CONFIG.data.get("nwb"), EXPORT_RECORDINGS)
    if _nwb_problems:
        stop_run("exports.nwb is on, but:\n  " + "\n  ".join(_nwb_problems))
    NWB_INPUTS = NwbExportInputs.from_config(CONFIG)

    rule export_nwb:
        input:
            results="{outdir}/results.h5",
            footage=footage_inputs,
            metadata=lambda w: sidecar_inputs(recording(w)),
            angles=lambda w: (
                [f"{w.outdir}/{NEUROMECHFLY_FILES[0]}"] if FLAGS["neuromechfly"] else []
            ),
        output:
            output=f"{{outdir}}/{NWB_FILE}",
        log:
            "{outdir}/logs/export_nwb.log",
        benchmark:
            "{outdir}/benchmarks/export_nwb.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 1
        resources:
            mem_mb=2000,
            runtime=15,
        params:
            stage=as_is(NWB_INPUTS.rule_params()),
            runtime=lambda wildcards, input: NWB_INPUTS.runtime,
            recording=lambda w: str(recording(w).path),
            demo=lambda w: recording(w).demo,
        script:
            "../../scripts/export_nwb.py"
