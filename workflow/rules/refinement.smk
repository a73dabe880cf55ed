# refinement: every frame at once (robust reprojection, temporal smoothness, constant
# bone lengths, the tethered thorax held still), from the triangulation's 3D and
# inlier views, pose2d's 2D and confidences and the final rig. Assemble prefers its
# 3D over the triangulation's. CPU only.


if FLAGS["refinement"]:

    rule refinement:
        input:
            unpack(refinement_inputs),
        output:
            out=artifact("refinement"),
        log:
            "{outdir}/logs/refinement.log",
        benchmark:
            "{outdir}/benchmarks/refinement.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 2
        resources:
            mem_mb=job_mem_mb("refinement"),
            runtime=60,
        params:
            **job_params("refinement"),
        script:
            "../../scripts/refinement.py"
