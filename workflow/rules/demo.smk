# The embedded demo recording: synthetic footage of a walking fly rendered through the
# configured rig, its 2D keypoints as DeepLabCut CSVs, and the 3D truth. Generated
# only when the recordings list holds a {path: ..., demo: true} entry.

from flylib.pipeline.demo import demo_files
from flylib.pipeline.demo import DemoInputs

DEMO = next((r for r in RECORDINGS if r.demo), None)
DEMO_OUTPUTS: list[str] = []
DEMO_FOOTAGE: list[str] = []
DEMO_TRUTH: str | None = None
DEMO_VIDEO_SPEED: float | None = None

if DEMO is not None:
    try:
        DEMO_INPUTS = DemoInputs.from_config(CONFIG)
        _demo_names = demo_files(CONFIG)
    except FlylibError as exc:
        stop_run(str(exc))
    DEMO_OUTPUTS = [str(DEMO.path / name) for names in _demo_names.values() for name in names]
    DEMO_FOOTAGE = [str(DEMO.path / name) for name in _demo_names["footage"]]
    DEMO_TRUTH = str(DEMO.path / _demo_names["truth"][0])
    DEMO_VIDEO_SPEED = DEMO_INPUTS.settings["video_speed"]

    rule demo:
        output:
            DEMO_OUTPUTS,
        log:
            str(DEMO.outdir / "logs" / "demo.log"),
        benchmark:
            str(DEMO.outdir / "benchmarks" / "demo.tsv")
        conda:
            "../../envs/flylib.yaml"
        resources:
            mem_mb=2000,
            runtime=15,
        params:
            stage=as_is(DEMO_INPUTS.rule_params()),
            runtime=lambda wildcards, input: DEMO_INPUTS.runtime,
            out=lambda wildcards, output: str(Path(output[0]).parent),
        script:
            "../../scripts/demo.py"
