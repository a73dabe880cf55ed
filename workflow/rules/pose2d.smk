# pose2d: 2D keypoints per recording, from the detector or another tool's files.
# Its params leave out performance knobs (batch_size, decode_buffer, device) and the
# camera rig, so editing those re-runs no detection.


if FLAGS["pose2d"]:

    rule pose2d:
        input:
            recording_inputs,
        output:
            artifact("pose2d"),
        params:
            run=command("pose2d.py"),
            stage=stage_params("pose2d"),
            import_spec=pose2d_import,
            recording=lambda w: str(recording(w).path),
        log:
            "{outdir}/logs/pose2d.log",
        benchmark:
            "{outdir}/benchmarks/pose2d.tsv"
        threads: 2
        resources:
            mem_mb=8000,
            runtime=120,
            gpu=pose2d_gpus,
        conda:
            "../../envs/pose2d.yaml"
        shell:
            "{params.run}"
            " --recording {params.recording:q} --import-spec {params.import_spec:q}"
            " --out {output:q} --snapshot-dir {wildcards.outdir:q} 2> {log:q}"
