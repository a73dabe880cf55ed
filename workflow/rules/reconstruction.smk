# Geometry stages: bundle adjustment, pictorial structures, triangulation. CPU only.
# Triangulation reads pictorial-structures 2D only while that stage is on, and the
# bundle-adjusted rig only while bundle adjustment is on (else the config rig).


if FLAGS["bundle_adjustment"]:

    rule bundle_adjustment:
        input:
            pose2d=artifact("pose2d"),
            calibration=calibration_inputs,
        output:
            out=artifact("bundle_adjustment"),
        log:
            "{outdir}/logs/bundle_adjustment.log",
        benchmark:
            "{outdir}/benchmarks/bundle_adjustment.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 1
        resources:
            mem_mb=job_mem_mb("bundle_adjustment"),
            runtime=60,
        params:
            **job_params("bundle_adjustment"),
        script:
            "../../scripts/bundle_adjustment.py"


if SESSIONS:
    from flylib.pipeline.session_calibration import (
        SessionCalibrationInputs,
        SessionSummaryInputs,
    )

    SESSION_INPUTS = SessionCalibrationInputs.from_config(CONFIG)
    SESSION_SUMMARY_INPUTS = SessionSummaryInputs.from_config(CONFIG)

    # One solve per session over frames sampled from every member; its rig replaces
    # each member's own in triangulation, refinement and assembly (rig_artifact).
    rule session_calibration:
        input:
            unpack(PLAN.session_inputs("session_calibration")),
        output:
            out="{sessiondir}/session_calibration.h5",
            calibration="{sessiondir}/calibration.toml",
        log:
            "{sessiondir}/logs/session_calibration.log",
        benchmark:
            "{sessiondir}/benchmarks/session_calibration.tsv"
        conda:
            "../../envs/flylib.yaml"
        threads: 1
        resources:
            mem_mb=job_mem_mb("bundle_adjustment"),
            runtime=60,
        params:
            stage=as_is(SESSION_INPUTS.rule_params()),
            runtime=lambda wildcards, input: SESSION_INPUTS.runtime_options,
            members=lambda w: json.dumps(session(w).ids),
            recordings=lambda w: json.dumps([str(r.path) for r in session(w).members]),
            name=lambda w: session(w).name,
        script:
            "../../scripts/session_calibration.py"

    # The held-out-view error with each member's own rig and with the session's.
    rule session_summary:
        input:
            unpack(PLAN.session_inputs("session_summary")),
        output:
            out="{sessiondir}/session_summary.json",
        log:
            "{sessiondir}/logs/session_summary.log",
        benchmark:
            "{sessiondir}/benchmarks/session_summary.tsv"
        conda:
            "../../envs/flylib.yaml"
        threads: 1
        resources:
            mem_mb=2000,
            runtime=30,
        params:
            stage=as_is(SESSION_SUMMARY_INPUTS.rule_params()),
            runtime=lambda wildcards, input: None,
            members=lambda w: json.dumps(session(w).ids),
            name=lambda w: session(w).name,
        script:
            "../../scripts/session_summary.py"


if FLAGS["pictorial_structures"]:

    rule pictorial_structures:
        input:
            unpack(reconstruction_inputs("pictorial_structures")),
        output:
            out=artifact("pictorial_structures"),
        log:
            "{outdir}/logs/pictorial_structures.log",
        benchmark:
            "{outdir}/benchmarks/pictorial_structures.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 1
        resources:
            mem_mb=2000,
            runtime=60,
        params:
            **job_params("pictorial_structures"),
        script:
            "../../scripts/pictorial_structures.py"


if FLAGS["triangulation"]:

    rule triangulation:
        input:
            unpack(reconstruction_inputs("triangulation")),
            unpack(corrections_inputs),
        output:
            out=artifact("triangulation"),
        log:
            "{outdir}/logs/triangulation.log",
        benchmark:
            "{outdir}/benchmarks/triangulation.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 2
        resources:
            mem_mb=job_mem_mb("triangulation"),
            runtime=30,
        params:
            **job_params("triangulation"),
        script:
            "../../scripts/triangulation.py"
