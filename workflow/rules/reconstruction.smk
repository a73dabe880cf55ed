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
            stage=stage_params("bundle_adjustment"),
            runtime=job_runtime("bundle_adjustment"),
            recording=lambda w: str(recording(w).path),
        script:
            "../../scripts/bundle_adjustment.py"


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
            stage=stage_params("pictorial_structures"),
            runtime=job_runtime("pictorial_structures"),
            recording=lambda w: str(recording(w).path),
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
            stage=stage_params("triangulation"),
            runtime=job_runtime("triangulation"),
            recording=lambda w: str(recording(w).path),
        script:
            "../../scripts/triangulation.py"
