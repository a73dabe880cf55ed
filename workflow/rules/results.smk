# assemble: results.h5 (schema v2, readable by PoseResult.load) from the stage
# artifacts of the enabled stages, plus the per-recording summary: summary.png,
# calibration.toml (the final rig in Anipose format) and summary.json. For the demo
# it also prints the 3D error against the truth.


rule assemble:
    input:
        unpack(assemble_inputs),
    output:
        results="{outdir}/results.h5",
        summary="{outdir}/summary.json",
        figure=report(
            "{outdir}/summary.png",
            caption="../report/summary.rst",
            category="Summary figures",
            labels={"recording": "{outdir}", "figure": "summary"},
        ),
        calibration="{outdir}/calibration.toml",
        suspects="{outdir}/suspects.csv",
        # the config snapshot: written last, by this rule only, so it always
        # describes the results beside it (issue 14: one owner per output)
        snapshot="{outdir}/config.yaml",
    log:
        "{outdir}/logs/assemble.log",
    benchmark:
        "{outdir}/benchmarks/assemble.tsv"
    group:
        RECORDING_GROUP
    conda:
        "../../envs/flylib.yaml"
    resources:
        mem_mb=job_mem_mb("assemble"),
        runtime=15,
    params:
        **job_params("assemble"),
        # the snapshot's text: derived (a function of the input), so it re-runs nothing
        config_text=lambda wildcards, input: CONFIG.snapshot_text(),
    script:
        "../../scripts/assemble.py"
