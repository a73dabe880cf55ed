# neuromechfly (off by default): the 3D aligned to NeuroMechFly's template body and its
# 42 leg joint angles by inverse kinematics: neuromechfly.h5, joint_angles.csv (flygym's
# kinematic-replay layout) and joint_angles.png (angle traces per leg, in the report).


if FLAGS["neuromechfly"]:

    rule neuromechfly:
        input:
            results="{outdir}/results.h5",
        output:
            h5="{outdir}/neuromechfly.h5",
            csv="{outdir}/joint_angles.csv",
            figure=report(
                "{outdir}/joint_angles.png",
                caption="../report/neuromechfly.rst",
                category="Joint angles",
                labels={"recording": "{outdir}", "figure": "neuromechfly"},
            ),
        log:
            "{outdir}/logs/neuromechfly.log",
        benchmark:
            "{outdir}/benchmarks/neuromechfly.tsv"
        group:
            RECORDING_GROUP
        conda:
            "../../envs/flylib.yaml"
        threads: 1
        resources:
            mem_mb=3000,
            runtime=30,
        params:
            **job_params("neuromechfly", recording_path=False),
        script:
            "../../scripts/neuromechfly.py"
