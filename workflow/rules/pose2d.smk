# pose2d: 2D keypoints per recording, from the detector or another tool's files.
# Its params leave out performance knobs (batch_size, decode_buffer, device) and the
# camera rig, so editing those re-runs no detection. While pictorial structures is on
# it also writes the detector's candidate peaks, as a second output: turning PS on
# runs the detection once more for them, turning it off again re-runs nothing here.


if FLAGS["pose2d"]:

    rule pose2d:
        input:
            recording_inputs,
        output:
            **pose2d_outputs(),
        log:
            "{outdir}/logs/pose2d.log",
        benchmark:
            "{outdir}/benchmarks/pose2d.tsv"
        group:
            pose2d_group
        conda:
            "../../envs/flylib.yaml"
        threads: 2
        resources:
            mem_mb=pose2d_mem_mb,
            runtime=pose2d_runtime,
            gpu=pose2d_gpus,
        params:
            **job_params("pose2d"),
            import_spec=pose2d_import,
        script:
            "../../scripts/pose2d.py"
