# Geometry stages: bundle adjustment, pictorial structures, triangulation. CPU only.
# Triangulation reads pictorial-structures 2D only while that stage is on, and the
# bundle-adjusted rig only while bundle adjustment is on (else the config rig).


if FLAGS["bundle_adjustment"]:

    rule bundle_adjustment:
        input:
            pose2d=artifact("pose2d"),
            calibration=calibration_inputs,
        output:
            artifact("bundle_adjustment"),
        params:
            run=command("bundle_adjustment.py"),
            stage=stage_params("bundle_adjustment"),
            recording=lambda w: str(recording(w).path),
        log:
            "{outdir}/logs/bundle_adjustment.log",
        benchmark:
            "{outdir}/benchmarks/bundle_adjustment.tsv"
        resources:
            mem_mb=2000,
            runtime=60,
        conda:
            "../../envs/geometry.yaml"
        shell:
            "{params.run}"
            " --pose2d {input.pose2d:q} --recording {params.recording:q}"
            " --out {output:q} 2> {log:q}"


if FLAGS["pictorial_structures"]:

    rule pictorial_structures:
        input:
            unpack(reconstruction_inputs("pictorial_structures")),
        output:
            artifact("pictorial_structures"),
        params:
            run=command("pictorial_structures.py"),
            stage=stage_params("pictorial_structures"),
            recording=lambda w: str(recording(w).path),
            rig=optional_arg("--bundle-adjustment", "bundle_adjustment"),
        log:
            "{outdir}/logs/pictorial_structures.log",
        benchmark:
            "{outdir}/benchmarks/pictorial_structures.tsv"
        resources:
            mem_mb=2000,
            runtime=60,
        conda:
            "../../envs/geometry.yaml"
        shell:
            "{params.run}"
            " --pose2d {input.pose2d:q} --candidates {input.candidates:q} {params.rig}"
            " --recording {params.recording:q}"
            " --out {output:q} 2> {log:q}"


if FLAGS["triangulation"]:

    rule triangulation:
        input:
            unpack(reconstruction_inputs("triangulation")),
            unpack(corrections_inputs),
        output:
            artifact("triangulation"),
        params:
            run=command("triangulation.py"),
            stage=stage_params("triangulation"),
            recording=lambda w: str(recording(w).path),
            rig=optional_arg("--bundle-adjustment", "bundle_adjustment"),
            points=optional_arg("--pictorial-structures", "pictorial_structures"),
            corrections=optional_arg("--corrections", "corrections"),
        log:
            "{outdir}/logs/triangulation.log",
        benchmark:
            "{outdir}/benchmarks/triangulation.tsv"
        resources:
            mem_mb=2000,
            runtime=30,
        conda:
            "../../envs/geometry.yaml"
        shell:
            "{params.run}"
            " --pose2d {input.pose2d:q} {params.rig} {params.points} {params.corrections}"
            " --recording {params.recording:q}"
            " --out {output:q} 2> {log:q}"
