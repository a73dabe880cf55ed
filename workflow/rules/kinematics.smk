# kinematics: the body frame (thorax-coxa centroid, x anterior, z dorsal) and joint
# angles from results.h5: kinematics.h5, angles.csv (Anipose's angles layout) and
# angles.png (angle traces per leg, in the report).


if FLAGS["kinematics"]:

    rule kinematics:
        input:
            results="{outdir}/results.h5",
        output:
            h5="{outdir}/kinematics.h5",
            csv="{outdir}/angles.csv",
            figure=report(
                "{outdir}/angles.png",
                caption="../report/angles.rst",
                category="Joint angles",
                labels={"recording": "{outdir}", "figure": "angles"},
            ),
        log:
            "{outdir}/logs/kinematics.log",
        benchmark:
            "{outdir}/benchmarks/kinematics.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 1
        resources:
            mem_mb=job_mem_mb("kinematics"),
            runtime=15,
        params:
            **job_params("kinematics", recording_path=False),
        script:
            "../../scripts/kinematics.py"
