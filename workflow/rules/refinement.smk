# refinement: every frame at once (robust reprojection, temporal smoothness, constant
# bone lengths, the tethered thorax held still), from the triangulation's 3D and
# inlier views, pose2d's 2D and confidences and the final rig. Assemble prefers its
# 3D over the triangulation's. CPU only.


if FLAGS["refinement"]:

    rule refinement:
        input:
            unpack(refinement_inputs),
        output:
            artifact("refinement"),
        log:
            "{outdir}/logs/refinement.log",
        benchmark:
            "{outdir}/benchmarks/refinement.tsv"
        conda:
            "../../envs/geometry.yaml"
        resources:
            mem_mb=3000,
            runtime=60,
        params:
            run=command("refinement.py"),
            stage=stage_params("refinement"),
            recording=lambda w: str(recording(w).path),
            rig=optional_arg("--bundle-adjustment", "bundle_adjustment"),
        shell:
            "{params.run}"
            " --pose2d {input.pose2d:q} --triangulation {input.triangulation:q} {params.rig}"
            " --recording {params.recording:q}"
            " --out {output:q} 2> {log:q}"
