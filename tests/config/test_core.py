"""Config: loading (YAML/TOML), validation messages, typed views, stage_params, snapshots, schema."""

from __future__ import annotations

import copy
import fnmatch
import json
import re
import tomllib
from pathlib import Path

import pytest
import tomli_w

from flylib.config import DEFAULT_CONFIG_PATH, PARAM_STAGES, STAGE_DEFAULTS, STAGES, Config
from flylib.errors import ConfigError
from flylib.pipeline.inputs import stage_params
from flylib.pipeline.planning import config_rig
from flylib.skeleton import Skeleton

from rig_constants import DISTANCE, VIEWS

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def default() -> Config:
    return Config.default()


@pytest.fixture()
def data(default) -> dict:
    return copy.deepcopy(default.data)


def all_params(config: Config) -> dict:
    return {stage: stage_params(config, stage) for stage in PARAM_STAGES}


# -- the default config --------------------------------------------------------


def test_packaged_default_is_a_file_in_the_package_identical_to_the_users_copy():
    # A symlink breaks in wheels and on Windows; config/config.yaml is the copy users edit.
    assert DEFAULT_CONFIG_PATH.parent == REPO / "src" / "flylib"
    assert DEFAULT_CONFIG_PATH.is_file() and not DEFAULT_CONFIG_PATH.is_symlink()
    user = REPO / "config" / "config.yaml"
    assert DEFAULT_CONFIG_PATH.read_bytes() == user.read_bytes(), (
        f"{DEFAULT_CONFIG_PATH} and {user} differ: edit one, then copy it over the other"
    )
    package_data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]
    assert any(
        fnmatch.fnmatch(DEFAULT_CONFIG_PATH.name, pattern) for pattern in package_data["flylib"]
    )


def test_skeleton_fly_is_the_default_configs_skeleton(default):
    assert Skeleton.fly() == default.skeleton() == Skeleton.from_config(default)
    assert Skeleton.fly().n_points == 38


def test_default_config_is_the_seven_camera_fly_rig(default):
    assert default.view_names() == list(VIEWS)
    assert default.source_patterns()["vid_f"] == "camera_3.mp4"
    assert len(default.source_patterns()) == 7
    defaults, cameras = default.camera_table()
    assert defaults["distance"] == pytest.approx(DISTANCE)
    assert cameras["lh"] == {"azimuth_deg": 120}
    assert default.triangulation.method == "ransac"
    assert default.triangulation.ransac_threshold == 15.0
    assert default.triangulation.min_inliers == 2
    assert isinstance(default.data["recordings"], list) and default.data["recursive"] is False
    assert default.data["outdir"] is None
    assert default.skeleton() == Skeleton.fly()


def test_stage_flags_default_pictorial_off(default, data):
    assert STAGES[0] == "pose2d" and STAGE_DEFAULTS["pictorial_structures"] is False
    assert default.stage_flags() == {
        "pose2d": True,
        "bundle_adjustment": True,
        "pictorial_structures": False,
        "triangulation": True,
        "refinement": True,
        "kinematics": True,
        "neuromechfly": False,
        "visualization": True,
    }
    del data["pipeline"]
    assert Config.from_dict(data).stage_flags() == STAGE_DEFAULTS


def test_refinement_needs_triangulation_and_kinematics_some_3d(data):
    data["pipeline"]["do_triangulation"] = False
    flags = Config.from_dict(data).stage_flags()
    assert flags["refinement"] is False and flags["kinematics"] is False
    data["pipeline"]["do_pictorial_structures"] = True
    assert Config.from_dict(data).stage_flags()["kinematics"] is True


def test_refinement_and_kinematics_tables_are_checked(data):
    data["refinement"] = {"smooth_order": 3, "rigid_points": ["lf_thorax_coxa", "nose"], "lossy": 1}
    data["kinematics"] = {
        "angles": {
            "bad": ["lf_claw", "lf_femur_tibia"],
            "ok": ["lf_claw", "lf_femur_tibia", "lf_tibia_tarsus"],
        },
        "body_frame": {"origin": ["lf_thorax_coxa"]},
    }
    with pytest.raises(ConfigError) as err:
        Config.from_dict(data)
    text = str(err.value)
    for needle in (
        "refinement.smooth_order",
        "refinement.rigid_points: unknown point 'nose'",
        "refinement.lossy: unknown parameter",
        "kinematics.angles.bad: expected three point names",
        "kinematics.body_frame: missing posterior",
    ):
        assert needle in text, needle
    assert "kinematics.angles.ok" not in text


def test_typed_views(default, data):
    ba = default.bundle_adjustment
    assert ba.least_squares == {"max_nfev": 2000, "loss": "linear"}
    assert ba.fixed == ("*.intr",) and ba.max_frames == 200 and ba.frame_sampling == "even"
    assert len(ba.points_to_use) == 32
    assert default.pose2d.precision == "bfloat16" and default.pose2d.batch_size == 16
    assert default.io.image_workers is None
    assert default.pictorial_structures.k == 5 and default.pictorial_structures.solver_kwargs() == {
        "temporal": False,
        "lam": 1.0,
        "bone_max_frames": 100,
    }
    data["triangulation"].update(method="greedy", reproj_threshold=30, max_drops=2)
    data["pictorial_structures"]["huber"] = 3
    data["io"]["image"]["workers"] = 4
    config = Config.from_dict(data)
    assert config.triangulation.reproj_threshold == 30.0
    assert isinstance(config.triangulation.reproj_threshold, float)
    assert config.triangulation.method_params() == {
        "method": "greedy",
        "weigh_by_confidence": False,
        "reproj_threshold": 30.0,
        "max_drops": 2,
    }
    assert config.pictorial_structures.solver_kwargs()["huber"] == 3.0
    assert config.io.image_workers == 4
    # a table left out falls back to the dataclass defaults
    del data["triangulation"]
    assert Config.from_dict(data).triangulation.method == "ransac"


# -- stage_params ----------------------------------------------------------------


def test_stage_params_cover_every_workflow_stage_and_are_json(default):
    params = all_params(default)
    assert set(params) == {
        "pose2d",
        "bundle_adjustment",
        "pictorial_structures",
        "triangulation",
        "refinement",
        "assemble",
        "kinematics",
        "neuromechfly",
        "visualization",
    }
    for value in params.values():
        assert json.loads(json.dumps(value)) == value
    text = json.dumps(params["pose2d"])
    for knob in ("batch_size", "decode_buffer", "device", "compile", "workers"):
        assert knob not in text
    assert "candidates" not in params["pose2d"] and "pictorial" not in text
    assert params["pose2d"]["views"] == default.view_names()
    assert params["triangulation"]["triangulation"] == {
        "method": "ransac",
        "min_inliers": 2,
        "ransac_threshold": 15.0,
        "weigh_by_confidence": False,
    }


@pytest.mark.parametrize(
    ("section", "key", "value"),
    [
        ("pose2d", "batch_size", 64),
        ("pose2d", "decode_buffer", 1),
        ("pose2d", "device", "cuda:1"),
        ("pose2d", "compile", False),
        ("bundle_adjustment", "verbose", 2),
    ],
)
def test_performance_knobs_change_no_stage_params(default, data, section, key, value):
    data[section][key] = value
    assert all_params(Config.from_dict(data)) == all_params(default)


def test_io_workers_change_no_stage_params(default, data):
    data["io"]["image"]["workers"] = 8
    assert all_params(Config.from_dict(data)) == all_params(default)


def changed_stages(before: Config, after: Config) -> set[str]:
    a, b = all_params(before), all_params(after)
    return {stage for stage in PARAM_STAGES if a[stage] != b[stage]}


def test_ransac_threshold_changes_only_triangulation_and_refinement(default, data):
    data["triangulation"]["ransac_threshold"] = 20.0
    # refinement's held-out-view check re-runs the triangulation without each view
    assert changed_stages(default, Config.from_dict(data)) == {"triangulation", "refinement"}


def test_knob_of_another_method_changes_nothing(default, data):
    data["triangulation"]["reproj_threshold"] = 12.0  # greedy only; default method is ransac
    assert changed_stages(default, Config.from_dict(data)) == set()


def test_rig_change_spares_pose2d(default, data):
    data["cameras"]["lf"]["azimuth_deg"] = 50
    assert changed_stages(default, Config.from_dict(data)) == {"bundle_adjustment", "assemble"}


def test_rig_reaches_triangulation_when_bundle_adjustment_is_off(data):
    data["pipeline"]["do_bundle_adjustment"] = False
    before = Config.from_dict(data)
    data["cameras"]["lf"]["azimuth_deg"] = 50
    assert changed_stages(before, Config.from_dict(data)) == {
        "bundle_adjustment",
        "pictorial_structures",
        "triangulation",
        "refinement",
        "assemble",
    }


def test_refinement_weight_changes_only_refinement(default, data):
    data["refinement"]["smooth_weight"] = 0.5
    assert changed_stages(default, Config.from_dict(data)) == {"refinement"}


def test_toggling_pictorial_leaves_pose2d_params_alone(default, data):
    # the candidates are an extra pose2d output named by k while PS is on (the workflow
    # re-runs the detection when that file is missing), so neither the toggle nor k
    # touches pose2d's params
    data["pipeline"]["do_pictorial_structures"] = True
    config = Config.from_dict(data)
    assert stage_params(config, "triangulation")["points_from"] == "pictorial_structures"
    assert changed_stages(default, config) == {"triangulation"}
    data["pictorial_structures"]["k"] = 8
    assert changed_stages(config, Config.from_dict(data)) == {"pictorial_structures"}


def test_palette_change_touches_only_outputs_that_draw_it(default, data):
    data["skeleton"]["limb_palette"]["rf_leg"] = "#000000"
    assert changed_stages(default, Config.from_dict(data)) == {"assemble", "visualization"}


def test_stage_params_ignore_mapping_key_order(default, data):
    data["triangulation"] = dict(reversed(list(data["triangulation"].items())))
    data["pose2d"]["output_points"]["f"] = dict(
        reversed(list(data["pose2d"]["output_points"]["f"].items()))
    )
    assert all_params(Config.from_dict(data)) == all_params(default)


def test_camera_order_is_part_of_the_params(default, data):
    cams = data["cameras"]
    data["cameras"] = {
        "defaults": cams["defaults"],
        **{k: cams[k] for k in reversed(default.view_names())},
    }
    assert "pose2d" in changed_stages(default, Config.from_dict(data))


def test_unknown_stage_is_rejected(default):
    with pytest.raises(ValueError, match="unknown stage 'pose3d'"):
        stage_params(default, "pose3d")


# -- validation ------------------------------------------------------------------


def _set(path: str, value):
    def mutate(d: dict) -> None:
        *parents, last = path.split(".")
        for key in parents:
            d = d[int(key)] if isinstance(d, list) else d[key]
        if isinstance(d, list):
            d[int(last)] = value
        else:
            d[last] = value

    return mutate


def _rename_key(path: str, old: str, new: str):
    def mutate(d: dict) -> None:
        for key in path.split("."):
            d = d[key]
        d[new] = d.pop(old)

    return mutate


INVALID = [
    (_set("triangulaton", {}), "triangulaton: unknown top-level table"),
    (_set("triangulation.ransac_treshold", 10), "triangulation.ransac_treshold: unknown parameter"),
    (_set("pictorial_structures.lamda", 2), "pictorial_structures.lamda: unknown parameter"),
    (_set("pipeline.do_pose3d", True), "pipeline.do_pose3d: unknown parameter"),
    (_set("pose2d.batchsize", 8), "pose2d.batchsize: unknown parameter"),
    (_set("bundle_adjustment.max_nfevs", 10), "bundle_adjustment.max_nfevs: unknown parameter"),
    (_set("bundle_adjustment.jac", "3-point"), "bundle_adjustment.jac: unknown parameter"),
    (_set("bundle_adjustment.loss", "hubber"), "bundle_adjustment.loss: expected one of 'linear'"),
    (_set("bundle_adjustment.ftol", "1e-x"), "bundle_adjustment.ftol: expected a number"),
    (
        _set("triangulation.min_inliers", "two"),
        "triangulation.min_inliers: expected an integer >= 2",
    ),
    (_set("triangulation.min_inliers", 1), "triangulation.min_inliers: expected an integer >= 2"),
    (
        _set("triangulation.ransac_threshold", -1.0),
        "triangulation.ransac_threshold: expected a number > 0",
    ),
    (
        _set("triangulation.weigh_by_confidence", "yes"),
        "triangulation.weigh_by_confidence: expected true or false",
    ),
    (_set("pipeline.do_pose2d", 1), "pipeline.do_pose2d: expected true or false"),
    (_set("pose2d.batch_size", 1.5), "pose2d.batch_size: expected an integer >= 1"),
    (_set("pictorial_structures.k", True), "pictorial_structures.k: expected an integer >= 1"),
    (
        _set("bundle_adjustment.fixed", "*.intr"),
        "bundle_adjustment.fixed: expected a list of strings",
    ),
    (
        _set("triangulation.method", "ransack"),
        "triangulation.method: expected one of 'ransac', 'greedy', 'dlt'",
    ),
    (
        _set("bundle_adjustment.frame_sampling", "random"),
        "bundle_adjustment.frame_sampling: expected one of 'even'",
    ),
    (
        _set("pose2d.precision", "float64"),
        "pose2d.precision: expected one of 'float32', 'float16', 'bfloat16'",
    ),
    (
        _set("skeleton.limb_points.lf_leg.2", "lf_femurr"),
        "skeleton.limb_points.lf_leg: unknown point 'lf_femurr' (known: lf_thorax_coxa",
    ),
    (
        _set("bundle_adjustment.points_to_use.0", "lf_thorax"),
        "bundle_adjustment.points_to_use: unknown point 'lf_thorax'",
    ),
    (
        _rename_key("pose2d.output_points.f", "rf_claw", "rf_clow"),
        "pose2d.output_points.f.rf_clow: unknown point 'rf_clow'",
    ),
    (
        _set("pose2d.pathways.0.source", "vid_rhh"),
        "pose2d.pathways.rh.source: unknown source 'vid_rhh' (known: vid_rh,",
    ),
    (
        _set("pose2d.pathways.0.source", ["vid_rh"]),
        "pose2d.pathways.rh.source: unknown source ['vid_rh']",
    ),
    (
        _set("pose2d.pathways.4.preprocessor", "flop"),
        "pose2d.pathways.f_flip.preprocessor: unknown preprocessor 'flop' (known: flip)",
    ),
    (
        _set("pose2d.pathways.1.model", "sh8"),
        "pose2d.pathways.rm.model: unknown model 'sh8' (known: deepfly2d)",
    ),
    (
        _set("pose2d.output_points.f.rf_claw.pathway", "front"),
        "pose2d.output_points.f.rf_claw.pathway: unknown pathway 'front'",
    ),
    (
        _set("pose2d.output_points.rh.r_abdomen2.out_channel", 19),
        "pose2d.output_points.rh.r_abdomen2.out_channel: 19 is out of range for model 'deepfly2d' (n_out_channels 19",
    ),
    (
        _set("pose2d.output_points.rh.r_abdomen2.out_channel", -1),
        "pose2d.output_points.rh.r_abdomen2.out_channel: expected an integer >= 0",
    ),
    (
        _rename_key("pose2d.output_points", "f", "front"),
        "pose2d.output_points.front: unknown view 'front' (cameras: rh, rm",
    ),
    (
        _set("pose2d.models.0.n_out_channels", 0),
        "pose2d.models.deepfly2d.n_out_channels: expected an integer >= 1",
    ),
    (_set("sources.1.name", "vid_rh"), "sources[1].name: 'vid_rh' is defined twice"),
    (_set("pose2d.import", "dlc"), "pose2d.import: expected a mapping or null"),
    (_set("calibration", ["a.toml"]), "calibration: expected a mapping or null"),
    (_set("recordings", 5), "recordings: expected a list of recordings"),
    (_set("kinematics.allow_mirrored", "yes"), "kinematics.allow_mirrored: expected true or false"),
    (_set("neuromechfly.allow_mirrored", 1), "neuromechfly.allow_mirrored: expected true or false"),
    (_set("demo", "yes"), "demo: expected a mapping or null"),
    (_set("recursive", "no"), "recursive: expected true or false"),
    (_set("outdir", 3), "outdir: expected a path template or null"),
    (_set("io.image.workers", -2), "io.image.workers: expected an integer >= 0"),
    (_set("triangulation", [1, 2]), "triangulation: expected a mapping"),
]


@pytest.mark.parametrize(("mutate", "message"), INVALID, ids=[m for _, m in INVALID])
def test_each_problem_is_reported_with_its_key_path(data, mutate, message):
    mutate(data)
    with pytest.raises(ConfigError) as info:
        Config.from_dict(data)
    assert any(p.startswith(message) for p in info.value.problems), info.value.problems


def test_least_squares_options_pass_through(data):
    data["bundle_adjustment"].update(f_scale=2.0, ftol=1e-6, method="trf", x_scale="jac")
    ba = Config.from_dict(data).bundle_adjustment
    assert ba.least_squares == {
        "max_nfev": 2000,
        "loss": "linear",
        "f_scale": 2.0,
        "ftol": 1e-6,
        "method": "trf",
        "x_scale": "jac",
    }


def test_all_problems_are_reported_together_one_line_each(data):
    data["triangulation"]["method"] = "ransack"
    data["pipeline"]["do_pose3d"] = True
    data["skeleton"]["limb_points"]["rf_leg"][0] = "rf_thorax"
    with pytest.raises(ConfigError) as info:
        Config.from_dict(data)
    assert len(info.value.problems) == 3
    lines = str(info.value).splitlines()
    assert lines[0] == "invalid config <dict> (3 problems; fix and re-run):"
    assert len(lines) == 4
    assert {line.strip().split(":")[0] for line in lines[1:]} == {
        "triangulation.method",
        "pipeline.do_pose3d",
        "skeleton.limb_points.rf_leg",
    }


def test_output_points_filled_twice_is_reported_from_yaml(tmp_path):
    text = DEFAULT_CONFIG_PATH.read_text()
    line = "      rf_claw: {pathway: f, out_channel: 4}\n"
    assert line in text
    path = tmp_path / "dup.yaml"
    path.write_text(
        text.replace(line, line + "      rf_claw: {pathway: f_flip, out_channel: 4}\n", 1)
    )
    with pytest.raises(
        ConfigError,
        match=r"pose2d\.output_points\.f\.rf_claw: \(view 'f', point 'rf_claw'\) is filled twice \(lines \d+ and \d+\)",
    ) as info:
        Config.from_yaml(path)
    assert str(path) in str(info.value)


def test_duplicate_key_anywhere_is_reported(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text(
        DEFAULT_CONFIG_PATH.read_text().replace(
            "  min_inliers: 2\n", "  min_inliers: 2\n  min_inliers: 3\n"
        )
    )
    with pytest.raises(ConfigError, match="triangulation.min_inliers: key given twice"):
        Config.from_yaml(path)


def test_skeleton_without_table_uses_fly_points(data):
    del data["skeleton"]
    config = Config.from_dict(data)
    assert config.skeleton() == Skeleton.fly()
    data["pose2d"]["output_points"]["f"]["rf_clow"] = {"pathway": "f", "out_channel": 4}
    with pytest.raises(ConfigError, match="unknown point 'rf_clow'"):
        Config.from_dict(data)


# -- files and formats -----------------------------------------------------------


def test_yaml_exponent_without_dot_reads_as_float(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(
        DEFAULT_CONFIG_PATH.read_text().replace(
            "  loss: linear\n", "  loss: linear\n  ftol: 1e-10\n"
        )
    )
    assert Config.from_yaml(path).bundle_adjustment.least_squares["ftol"] == 1e-10


def test_toml_config_gives_the_same_params(default, data, tmp_path):
    data.pop("outdir")  # TOML has no null: an absent key means the same
    path = tmp_path / "run.toml"
    path.write_text(tomli_w.dumps(data))
    config = Config.from_file(path)
    assert config.format == "toml" and config.source == path
    assert all_params(config) == all_params(default)


def test_file_errors_are_one_line_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="missing.yaml: config file not found"):
        Config.from_file(tmp_path / "missing.yaml")
    (tmp_path / "c.json").write_text("{}")
    with pytest.raises(
        ConfigError, match=r"unknown config format '\.json'; use a \.yaml, \.yml or \.toml file"
    ):
        Config.from_file(tmp_path / "c.json")
    (tmp_path / "bad.yaml").write_text("triangulation: {method: ransac\n")
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML .*line 2") as info:
        Config.from_file(tmp_path / "bad.yaml")
    assert "\n" not in str(info.value)
    (tmp_path / "bad.toml").write_text("[triangulation\n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        Config.from_file(tmp_path / "bad.toml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="the top level must be a mapping"):
        Config.from_file(tmp_path / "list.yaml")


def test_snapshot_is_byte_identical_to_the_source(tmp_path):
    raw = DEFAULT_CONFIG_PATH.read_bytes().replace(b"\n", b"\r\n")
    raw = raw.replace(b"# flylib default", "# flylib défault — µm".encode(), 1)
    src = tmp_path / "my config.yml"
    src.write_bytes(raw)
    config = Config.from_file(src)
    out = config.save_snapshot(tmp_path / "out")
    assert out == tmp_path / "out" / "config.yaml"
    assert out.read_bytes() == raw
    assert [p.name for p in out.parent.iterdir()] == ["config.yaml"]  # no temporary left behind


def test_toml_snapshot_replaces_a_stale_yaml_one(data, tmp_path):
    data.pop("outdir")
    src = tmp_path / "run.toml"
    src.write_text(tomli_w.dumps(data))
    outdir = tmp_path / "out"
    Config.default().save_snapshot(outdir)
    Config.from_toml(src).save_snapshot(outdir)
    assert sorted(p.name for p in outdir.iterdir()) == ["config.toml"]
    assert (outdir / "config.toml").read_bytes() == src.read_bytes()


def test_dict_config_snapshot_round_trips(data, tmp_path):
    data["triangulation"]["ransac_threshold"] = 11.5
    out = Config.from_dict(data).save_snapshot(tmp_path)
    assert Config.from_file(out).data == data
    data["cameras"]["defaults"]["look_at"] = (0.0, 0.0, 1.0)  # library users pass tuples
    out = Config.from_dict(data).save_snapshot(tmp_path)
    assert Config.from_file(out).data["cameras"]["defaults"]["look_at"] == [0.0, 0.0, 1.0]


# -- type errors: flylib's validator is the only one (no separate JSON schema) -------


TYPE_ERRORS = [
    ("triangulation.min_inliers", "two"),
    ("triangulation.method", "ransack"),
    ("pipeline.do_pose2d", "yes"),
    ("pose2d.batch_size", 1.5),
    ("pose2d.precision", "float64"),
    ("pictorial_structures.temporal", 1),
    ("bundle_adjustment.frame_sampling", "random"),
    ("bundle_adjustment.fixed", "*.intr"),
    ("pose2d.output_points.rh.r_abdomen2.out_channel", -1),
    ("recursive", "no"),
    ("outdir", 3),
    ("triangulaton", {}),
    ("io.image.workers", -2),
]


@pytest.mark.parametrize(("path", "value"), TYPE_ERRORS, ids=[p for p, _ in TYPE_ERRORS])
def test_validator_rejects_type_errors_naming_the_key(data, path, value):
    _set(path, value)(data)
    with pytest.raises(ConfigError) as info:
        Config.from_dict(data)
    assert any(p.startswith(path.split(".")[0]) for p in info.value.problems), info.value.problems


def test_there_is_no_second_validator_to_drift():
    assert not (REPO / "workflow" / "schemas").exists()
    rules = "".join(p.read_text() for p in (REPO / "workflow" / "rules").glob("*.smk"))
    assert "validate(" not in rules.replace("validate_config(", "")


def test_camera_group_delegates_to_cameras_module(default):
    rig = config_rig(default, image_sizes={name: (480, 960) for name in default.view_names()})
    assert list(rig.names) == default.view_names()


def test_error_messages_are_single_lines_per_problem(data):
    data["triangulation"]["min_inliers"] = "two"
    with pytest.raises(ConfigError) as info:
        Config.from_dict(data)
    (problem,) = info.value.problems
    assert re.fullmatch(
        r"triangulation\.min_inliers: expected an integer >= 2, got 'two' \(str\)", problem
    )


def test_least_squares_option_list_matches_scipy():
    import inspect

    from scipy.optimize import least_squares

    from flylib import config as config_module

    signature = set(inspect.signature(least_squares).parameters)
    options = set(config_module.LEAST_SQUARES_OPTIONS)
    assert signature - set(config_module.LEAST_SQUARES_RESERVED) == options & signature
    assert options - signature <= {"workers"}  # only in newer scipy releases


def test_pictorial_params_are_keywords_of_the_reconstructor(data):
    import inspect

    from flylib import pictorial

    data["pictorial_structures"].update(
        max_hyp=50, inlier_px=20.0, huber=3.0, mu=0.5, nms=2.0, bone_max_frames=None
    )
    kwargs = Config.from_dict(data).pictorial_structures.solver_kwargs()
    assert set(kwargs) == {
        "temporal",
        "lam",
        "bone_max_frames",
        "max_hyp",
        "inlier_px",
        "huber",
        "mu",
        "nms",
    }
    assert set(kwargs) <= set(inspect.signature(pictorial.reconstruct).parameters)


def test_videos_and_detection_plan_delegate_to_their_modules(default):
    from flylib.pipeline.inputs import stage_inputs
    from flylib.visualization.specs import video_specs

    assert [video.name for video in video_specs(default)] == ["pose2d", "pose3d"]
    plan = stage_inputs(default, "pose2d").detection_plan()
    assert list(plan.view_names) == default.view_names()
    assert list(plan.point_names) == list(Skeleton.fly().point_names)


@pytest.mark.parametrize(
    "path, value, key",
    [
        (("skeleton", "point_names", 0), ["lf_thorax_coxa"], "skeleton.point_names"),
        (("skeleton", "limb_points", "lf_leg", 0), ["lf_claw"], "skeleton.limb_points.lf_leg"),
        (("skeleton", "limb_points", "lf_leg", 0), {"a": 1}, "skeleton.limb_points.lf_leg"),
    ],
)
def test_a_point_name_that_is_not_a_string_is_one_line_naming_the_key(data, path, value, key):
    node = data
    for part in path[:-1]:
        node = node[part]
    node[path[-1]] = value
    with pytest.raises(ConfigError) as raised:
        Config.from_dict(data)
    assert any(line.strip().startswith(f"{key}:") for line in str(raised.value).splitlines())
