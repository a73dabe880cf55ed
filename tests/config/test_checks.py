"""Every key family the config checks know is rejected with one line naming its key,
before any job: flylib's validator (each key on its own) and the workflow's preflight
(what needs the whole config or the planned recordings); and config layers name the
user's own file that set the key."""

from __future__ import annotations

import copy
import functools
from dataclasses import fields
from pathlib import Path

import pytest
import yaml
from conftest import checkpoint_layout

from flylib.config import Config, validate_config
from flylib.config.constants import POSE2D_PLAN_KEYS, STAGES, TOP_LEVEL_KEYS
from flylib.config.layers import ConfigLayers, key_path
from flylib.config.params import LEAST_SQUARES_CHECKS, PARAM_TABLES
from flylib.errors import ConfigError
from flylib.pipeline.inputs import stage_inputs, stage_params
from flylib.pipeline.preflight import preflight_problems
from flylib.recordings import Recording

REPO = Path(__file__).resolve().parents[2]
BAD = {"not": "a valid value"}  # a mapping: wrong for every scalar / list parameter


@pytest.fixture(scope="module")
def default_data() -> dict:
    return Config.default().data


def edit(data: dict, path: str, value) -> dict:
    data = copy.deepcopy(data)
    node = data
    *parents, last = [int(k) if k.isdigit() else k for k in path.split(".")]
    for key in parents:
        node = node[key]
    node[last] = value
    return data


def edit_at(data: dict, *, path: str, value) -> dict:
    return edit(data, path, value)


def param_cases() -> list[tuple[str, object]]:
    """One bad value per typed parameter of every table the params dataclasses describe."""
    cases = []
    for table, cls in PARAM_TABLES.items():
        cases += [(f"{table}.{f.name}", BAD) for f in fields(cls) if "check" in f.metadata]
    cases += [
        (f"bundle_adjustment.{k}", "text" if k == "tr_options" else BAD)
        for k in LEAST_SQUARES_CHECKS
    ]
    cases += [(f"pipeline.do_{stage}", "yes") for stage in STAGES]
    return cases


# (key that must start the problem, mutation); the validator sees these alone
VALIDATOR_CASES = [
    ("sources", lambda d: edit(d, "sources", "camera_0.mp4")),
    ("sources[0].name", lambda d: edit(d, "sources.0", {"filename": "x.mp4"})),
    ("io.image.workers", lambda d: edit(d, "io.image.workers", -1)),
    ("skeleton", lambda d: edit(d, "skeleton.limb_points.lf_leg", ["nope"])),
    ("cameras.rh", lambda d: edit(d, "cameras.rh", 3)),
    ("pipeline.do_everything", lambda d: edit(d, "pipeline.do_everything", True)),
    ("pose2d.flux", lambda d: edit(d, "pose2d.flux", 1)),
    ("pose2d.preprocessors.flip.ops", lambda d: edit(d, "pose2d.preprocessors.0.ops", "fliplr")),
    (
        "pose2d.models.deepfly2d.n_out_channels",
        lambda d: edit(d, "pose2d.models.0.n_out_channels", 0),
    ),
    ("pose2d.pathways.rh.model", lambda d: edit(d, "pose2d.pathways.0.model", "nope")),
    (
        "pose2d.output_points.rh.rf_claw.out_channel",
        lambda d: edit(d, "pose2d.output_points.rh.rf_claw.out_channel", 99),
    ),
    ("pose2d.weights.sh8", lambda d: edit(d, "pose2d.weights", {"sh8": "x.tar"})),
    ("pose2d.weights", lambda d: edit(d, "pose2d.weights", "x.tar")),
    ("pose2d.import", lambda d: edit(d, "pose2d.import", "deepfly3d")),
    (
        "bundle_adjustment.points_to_use",
        lambda d: edit(d, "bundle_adjustment.points_to_use", ["nope"]),
    ),
    ("bundle_adjustment.jac", lambda d: edit(d, "bundle_adjustment.jac", "2-point")),
    ("visualization.videos", lambda d: edit(d, "visualization.videos", {"name": "x"})),
    ("calibration", lambda d: edit(d, "calibration", "rig.toml")),
    ("demo", lambda d: edit(d, "demo", [1])),
    ("recordings", lambda d: edit(d, "recordings", 3)),
    ("recursive", lambda d: edit(d, "recursive", "no")),
    ("outdir", lambda d: edit(d, "outdir", 3)),
    ("triangulaton", lambda d: edit(d, "triangulaton", {})),
    ("refinement.smooth_scale", lambda d: edit(d, "refinement.smooth_scale", -1)),
    ("refinement.rigid_points", lambda d: edit(d, "refinement.rigid_points", ["nope"])),
    (
        "kinematics.angles.a",
        lambda d: edit(d, "kinematics.angles", {"a": ["lf_claw", "lf_femur_tibia"]}),
    ),
    ("neuromechfly.still_tolerance", lambda d: edit(d, "neuromechfly.still_tolerance", 0)),
    ("neuromechfly.frame_rate", lambda d: edit(d, "neuromechfly.frame_rate", "fast")),
    ("exports.nwb", lambda d: edit(d, "exports", {"nwb": "yes"})),
    ("nwb.subject.sex", lambda d: edit(d, "nwb", {"subject": {"sex": "Q"}})),
    ("corrections", lambda d: edit(d, "corrections", 3)),
    ("pose2d.models.deepfly2d.subpixel", lambda d: edit(d, "pose2d.models.0.subpixel", "centroid")),
] + [(path, functools.partial(edit_at, path=path, value=value)) for path, value in param_cases()]


@pytest.mark.parametrize(("key", "mutate"), VALIDATOR_CASES, ids=[k for k, _ in VALIDATOR_CASES])
def test_validator_names_the_key_in_one_line(default_data, key, mutate):
    problems = validate_config(mutate(default_data))
    assert problems, f"{key}: accepted"
    assert any(p.startswith(key) for p in problems), problems
    assert all("\n" not in p for p in problems)


def recording(tmp_path: Path, *, spec=None, demo=False, sources=None, own=False) -> Recording:
    return Recording(
        id="rec",
        path=tmp_path,
        sources=sources if sources is not None else {"vid_rh": [tmp_path]},
        outdir=tmp_path / "out",
        import_spec=spec,
        demo=demo,
        extra={"where": "recordings[0]", "own_import": own},
    )


# (key, mutation, recording factory): what only the whole config or the plan can tell
PREFLIGHT_CASES = [
    ("cameras.rh.distance", lambda d: edit(d, "cameras.rh.distance", "far"), {}),
    ("cameras.rh.focal_length_px", lambda d: edit(d, "cameras.rh.focal_length_px", -1), {}),
    ("bundle_adjustment.fixed", lambda d: edit(d, "bundle_adjustment.fixed", ["xx.intr"]), {}),
    (
        "bundle_adjustment.shared",
        lambda d: edit(d, "bundle_adjustment.shared", [["rh.rvec", "rm.intr"]]),
        {},
    ),
    (
        "pose2d.import.format",
        lambda d: edit(d, "pose2d.import", {"format": "deepfly"}),
        {"spec": {"format": "deepfly"}},
    ),
    ("recordings[0].import.format", lambda d: d, {"spec": {"format": "deepfly"}, "own": True}),
    (
        "pose2d.models[0].n_out_channels",
        lambda d: edit(d, "pose2d.models", [{"name": "deepfly2d", "weights": "x.tar"}]),
        {},
    ),
    (
        "pose2d.weights.deepfly2d",
        lambda d: edit(d, "pose2d.weights", {"deepfly2d": "/no/such/sh8.tar"}),
        {},
    ),
    (
        "visualization.videos[0]",
        lambda d: edit(d, "visualization.videos.0.panels.0.view", "nope"),
        {},
    ),
    (
        "calibration.format",
        lambda d: edit(d, "calibration", {"file": "rig.toml", "format": "opencv"}),
        {},
    ),
    (
        "calibration.mirror",
        lambda d: edit(d, "calibration", {"file": "calib.pkl", "mirror": "yes"}),
        {},
    ),
    (
        "demo.frames",
        lambda d: edit(d, "demo", {"frames": 1}),
        {"demo": True, "spec": {"format": "dlc_csv"}},
    ),
    ("recordings[0]", lambda d: d, {"sources": {}}),
]


@pytest.mark.parametrize(
    ("key", "mutate", "rec"), PREFLIGHT_CASES, ids=[k for k, _, _ in PREFLIGHT_CASES]
)
def test_preflight_names_the_key_in_one_line(default_data, tmp_path, key, mutate, rec):
    config = Config.from_dict(mutate(default_data))
    problems = preflight_problems(config, [recording(tmp_path, **rec)], config.stage_flags())
    assert problems, f"{key}: accepted"
    assert any(p.startswith(key) for p in problems), problems
    assert all("\n" not in p for p in problems)


def test_preflight_passes_the_default_config_and_skips_the_detector_for_imported_2d(
    default_data, tmp_path, monkeypatch
):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    (tmp_path / "cache").mkdir()
    checkpoint_layout(tmp_path / "cache" / "sh8_deepfly.tar")  # the published checkpoint, cached
    config = Config.from_dict(default_data)
    assert preflight_problems(config, [recording(tmp_path)], config.stage_flags()) == []
    broken = Config.from_dict(edit(default_data, "pose2d.models", [{"name": "deepfly2d"}]))
    imported = recording(tmp_path, spec={"format": "dlc_csv", "image_size": [480, 960]})
    for view in broken.view_names():  # validation checks that the import's files exist
        (tmp_path / f"{view}.csv").touch()
    assert preflight_problems(broken, [imported], broken.stage_flags()) == []


def test_every_key_family_has_a_case():
    covered = {key_path(k)[0] for k, _ in VALIDATOR_CASES} | {
        key_path(k)[0] for k, _, _ in PREFLIGHT_CASES
    }
    assert set(TOP_LEVEL_KEYS) <= covered, set(TOP_LEVEL_KEYS) - covered
    pose2d = {
        str(key_path(k)[1])
        for k, *_ in [*VALIDATOR_CASES, *PREFLIGHT_CASES]
        if k.startswith("pose2d.")
    }
    assert set(POSE2D_PLAN_KEYS) <= pose2d, set(POSE2D_PLAN_KEYS) - pose2d


def test_weights_key_sets_a_checkpoint_without_restating_the_model(default_data, tmp_path):
    checkpoint = tmp_path / "sh8.tar"
    checkpoint_layout(checkpoint)
    config = Config.from_dict(edit(default_data, "pose2d.weights", {"deepfly2d": str(checkpoint)}))
    assert stage_inputs(config, "pose2d").detection_plan().models["deepfly2d"].weights == str(
        checkpoint
    )
    assert stage_params(config, "pose2d")["plan"]["weights"] == {"deepfly2d": str(checkpoint)}
    assert preflight_problems(config, [recording(tmp_path)], config.stage_flags()) == []


# -- layers: several files merged as Snakemake merges them -------------------------


def write(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


def test_layers_merge_tables_replace_lists_and_name_the_file_that_set_a_key(tmp_path):
    base = write(tmp_path / "base.yaml", (REPO / "config" / "config.yaml").read_text())
    mine = write(
        tmp_path / "mine.yaml",
        "pose2d:\n  models: [{name: deepfly2d, weights: x.tar}]\n"
        "triangulation:\n  ransac_threshold: 1.5e1\n",
    )
    layers = ConfigLayers.from_files([base, mine], overrides={"recursive": True})
    assert layers.data["pose2d"]["models"] == [{"name": "deepfly2d", "weights": "x.tar"}]
    assert (
        layers.data["pose2d"]["pathways"]
        == yaml.safe_load(Path(base).read_text())["pose2d"]["pathways"]
    )
    assert layers.data["triangulation"] == {
        "method": "ransac",
        "ransac_threshold": 15.0,
        **{
            k: v
            for k, v in Config.default().data["triangulation"].items()
            if k not in ("method", "ransac_threshold")
        },
    }
    assert layers.origin("triangulation.ransac_threshold: x") == mine
    assert layers.origin("triangulation.min_inliers: x") == base
    assert layers.origin("recursive: x") == "--config"
    assert layers.origin("pose2d.models[0].n_out_channels: x") == mine  # mine replaced the list
    assert layers.origin("pose2d.models.deepfly2d.n_out_channels: x") == mine
    report = layers.report(
        ["pose2d.models[0].n_out_channels: expected a positive integer, got None"]
    )
    assert "\n" not in report
    assert report.startswith(f"invalid config: {mine}: pose2d.models[0].n_out_channels")
    assert (
        f"replaces the whole pose2d.models list of {base}" in report and "pose2d.weights" in report
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "triangulation:\n  method: dlt\ntriangulation:\n  method: greedy\n",
            "triangulation: key given twice (lines 1 and 3)",
        ),
        ("triangulation:\n  method: [dlt\n", "not valid YAML"),
    ],
)
def test_layers_name_the_file_and_line_of_a_broken_file(tmp_path, text, message):
    path = write(tmp_path / "mine.yaml", text)
    with pytest.raises(ConfigError) as info:
        ConfigLayers.from_files([path])
    assert str(path) in str(info.value) and message in str(info.value)


def test_exponent_numbers_are_numbers(tmp_path, default_data):
    path = write(tmp_path / "mine.yaml", "bundle_adjustment:\n  ftol: 1e-8\n  f_scale: 1.5e1\n")
    layers = ConfigLayers.from_files([path])
    assert layers.data["bundle_adjustment"] == {"ftol": 1e-8, "f_scale": 15.0}
    assert validate_config({**default_data, **layers.data}) == []


# -- non-finite numbers (issue 37, case 5) ------------------------------------------------


def _numeric_fields() -> list[tuple[str, str, bool]]:
    """``(table, key, is_list)`` of every numeric field of every typed params table and
    every numeric least-squares option: a new field is covered here without a edit."""
    checks = [
        (table, f.name, f.metadata["check"])
        for table, cls in PARAM_TABLES.items()
        for f in fields(cls)
        if "check" in f.metadata
    ]
    checks += [("bundle_adjustment", key, check) for key, check in LEAST_SQUARES_CHECKS.items()]
    out = []
    for table, key, check in checks:
        if any(check(v) is None for v in (1, 2, 16, 1.0)):
            out.append((table, key, False))
        elif check([1.0]) is None:
            out.append((table, key, True))
    return out


NUMERIC_FIELDS = _numeric_fields()


def test_the_numeric_fields_are_found():
    keys = {f"{table}.{key}" for table, key, _ in NUMERIC_FIELDS}
    assert {"refinement.scale_px", "refinement.motion_scales", "triangulation.min_inliers"} <= keys
    assert "refinement.loss" not in keys and "triangulation.weigh_by_confidence" not in keys


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan"])
@pytest.mark.parametrize(("table", "key", "is_list"), NUMERIC_FIELDS)
def test_a_non_finite_number_is_one_line_naming_the_key(
    tmp_path, capsys, monkeypatch, table, key, is_list, value
):
    from flylib.cli import main
    from flylib.config.checks import INFINITE_OK

    monkeypatch.chdir(tmp_path)
    (tmp_path / "my.yaml").write_text(f"{table}:\n  {key}: {f'[{value}]' if is_list else value}\n")
    status = main(["check-config", str(REPO / "config" / "config.yaml"), "my.yaml"])
    err = capsys.readouterr().err.strip()
    where = f"{table}.{key}" + ("[0]" if is_list else "")
    if value == ".inf" and where in INFINITE_OK:
        assert status == 0, err
        return
    assert status == 1
    shown = {".inf": "inf", "-.inf": "-inf", ".nan": "nan"}[value]
    assert err.startswith(
        f"flylib check-config: invalid config: my.yaml: {where}: expected a finite"
    )
    assert f", got {shown}" in err and len(err.splitlines()) == 1, err


def test_inf_only_where_the_table_allows_it(default_data):
    from flylib.config.checks import INFINITE_OK

    data = copy.deepcopy(default_data)
    data["refinement"]["outlier_px"] = float("inf")
    assert "refinement.outlier_px" in INFINITE_OK and validate_config(data) == []
    assert Config.from_dict(data).refinement.outlier_px == float("inf")
    data["refinement"]["scale_px"] = float("inf")
    assert validate_config(data) == [
        "refinement.scale_px: expected a finite number (.inf is accepted only by "
        "refinement.outlier_px), got inf"
    ]


def test_a_non_finite_number_anywhere_in_the_config_is_refused(default_data):
    data = copy.deepcopy(default_data)
    data["cameras"]["defaults"]["distance"] = float("nan")
    data["visualization"]["kwargs"]["imshow"]["width"] = float("-inf")
    assert validate_config(data) == [
        "cameras.defaults.distance: expected a finite number (.inf is accepted only by "
        "refinement.outlier_px), got nan",
        "visualization.kwargs.imshow.width: expected a finite number (.inf is accepted only "
        "by refinement.outlier_px), got -inf",
    ]
