# visualization: the configured videos (visualization.videos) of one recording,
# drawn over its footage from results.h5. The demo's play in slow motion
# (demo.video_speed) unless the config sets a rate: 60 frames at 100 fps last 0.6 s.

if FLAGS["visualization"] and VIDEO_NAMES:

    rule visualization:
        input:
            results="{outdir}/results.h5",
            footage=footage_inputs,
        output:
            [
                report(
                    f"{{outdir}}/{name}.mp4",
                    caption="../report/video.rst",
                    category="Videos",
                    labels={"recording": "{outdir}", "video": name},
                )
                for name in VIDEO_NAMES
            ],
        log:
            "{outdir}/logs/visualization.log",
        benchmark:
            "{outdir}/benchmarks/visualization.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 2
        resources:
            mem_mb=4000,
            runtime=60,
        params:
            **job_params("visualization"),
            speed=lambda w: DEMO_VIDEO_SPEED if recording(w).demo else None,
        script:
            "../../scripts/visualization.py"
