"""NWB export (pynwb + ndx-pose), Anipose's 3D CSV layout, and reading flylib's outputs
back with the tools labs analyse with: pynwb, nwbinspector and movement.

The result under test is demo-like: the synthetic demo recording (40 frames of the
default 7-camera rig, DeepLabCut 2D with noise, dropouts and outliers) imported and
triangulated by flylib's own stages, with a few 3D points blanked so NaN is exercised.
"""

from __future__ import annotations

import copy
import json
import shutil
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pynwb
import pytest
import yaml

import flylib
from flylib.cli import main
from flylib.config import Config
from flylib.config.nwb_metadata import DEMO_METADATA, SIDECAR, recording_metadata
from flylib.errors import ConfigError
from flylib.interop.exports import points3d_table, write_dlc_views, write_points3d_csv
from flylib.interop.nwb import confidence_3d, write_nwb
from flylib.pipeline.export_nwb import NwbExportInputs, run_export_nwb
from flylib.pipeline.inputs import stage_inputs
from flylib.results import PoseResult

FRAMES = 40  # >= the 38 points, so every (time, point) series is time-major
FPS = 100.0
BLANKED = [(3, 0), (3, 5), (17, 12), (39, 37)]  # (frame, point) 3D points set to NaN


@pytest.fixture(scope="module")
def demo_result(tmp_path_factory):
    """A demo recording run through pose2d (DLC import) and triangulation; its results.h5."""
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.demo import demo_import_spec, make_demo
    from flylib.pipeline.pose2d import run_pose2d
    from flylib.pipeline.stage_helpers import run_inputs
    from flylib.pipeline.triangulation import run_triangulation

    config = Config.default()
    root = tmp_path_factory.mktemp("nwb")
    recording = root / "rec"
    out = recording / "flylib_outputs"
    make_demo(config, recording, frames=FRAMES)
    run_pose2d(
        stage_inputs(config, "pose2d"),
        recording,
        out / "stages" / "pose2d.h5",
        import_spec=demo_import_spec(config),
    )
    run_triangulation(
        run_inputs(config, "triangulation"),
        out / "stages" / "pose2d.h5",
        out / "stages" / "triangulation.h5",
        recording_dir=recording,
    )
    run_assemble(
        stage_inputs(config, "assemble"),
        {
            "pose2d": out / "stages" / "pose2d.h5",
            "triangulation": out / "stages" / "triangulation.h5",
        },
        out,
        recording_dir=recording,
    )
    result = PoseResult.load(out / "results.h5")
    for t, p in BLANKED:
        result.pts3d[t, p] = np.nan
    result.save(out / "results.h5")
    return {
        "config": config,
        "recording": recording,
        "results": out / "results.h5",
        "result": PoseResult.load(out / "results.h5"),
    }


@pytest.fixture(scope="module")
def nwb_file(demo_result):
    path = demo_result["recording"] / "flylib_outputs" / "results.nwb"
    run_export_nwb(
        NwbExportInputs.from_config(demo_result["config"]),
        demo_result["results"],
        path,
        recording_dir=demo_result["recording"],
    )
    return path


def _stack(container, names, attr="data"):
    return np.stack(
        [np.asarray(getattr(container.pose_estimation_series[n], attr)[:]) for n in names], 1
    )


# -- the NWB file --------------------------------------------------------------------


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_nwb_reads_back_with_pynwb_and_equals_results(demo_result, nwb_file):
    result = demo_result["result"]
    names = list(result.skeleton.point_names)
    assert all(np.isnan(result.pts3d[t, p]).all() for t, p in BLANKED)
    with pynwb.NWBHDF5IO(str(nwb_file), "r") as io:
        nwbfile = io.read()
        behavior = nwbfile.processing["behavior"]
        multi = behavior["MultiCameraPoseEstimation"]
        np.testing.assert_array_equal(_stack(multi, names), result.pts3d)  # NaN where NaN
        np.testing.assert_array_equal(
            _stack(multi, names, "confidence"), confidence_3d(result.reproj_error, result.pts3d)
        )
        assert np.isnan(_stack(multi, names, "confidence")[3, 0])
        for v, view in enumerate(result.cameras.names):
            pe = multi.pose_estimations[f"PoseEstimation_{view}"]
            np.testing.assert_array_equal(_stack(pe, names), result.pts2d[v])
            np.testing.assert_array_equal(_stack(pe, names, "confidence"), result.conf[v])
            np.testing.assert_array_equal(
                behavior[f"ReprojectionError_{view}"].data[:], result.reproj_error[v]
            )
            assert pe.skeleton is multi.skeleton and pe.device.name == f"camera_{view}"
            assert pe.pose_estimation_series[names[0]].unit == "pixels"
            # the source video is linked, relative to the NWB file, not copied
            video = pe.source_video
            (link,) = video.external_file[:]
            assert not Path(link).is_absolute()
            assert (nwb_file.parent / link).resolve() == (
                demo_result["recording"] / Path(link).name
            ).resolve()
            assert video.rate == FPS and video.device is pe.device
        assert np.isnan(result.pts2d).any()
        series = multi.pose_estimation_series[names[0]]
        assert series.rate == FPS and series.starting_time == 0.0
        assert "world frame" in series.reference_frame and series.confidence_definition.startswith(
            "exp("
        )
        skeleton = behavior["Skeletons"].skeletons[result.skeleton.name]
        assert list(skeleton.nodes[:]) == names
        np.testing.assert_array_equal(skeleton.edges[:], result.skeleton.bones)
        assert nwbfile.subject.subject_id == DEMO_METADATA["subject"]["subject_id"]
        assert nwbfile.session_start_time == datetime(2024, 1, 1, tzinfo=UTC)
        assert list(nwbfile.was_generated_by[0]) == ["flylib", flylib.__version__]
        assert str(demo_result["recording"].resolve()) in nwbfile.data_collection
        assert demo_result["config"].snapshot_text() in nwbfile.data_collection


def test_cameras_are_devices_with_the_final_calibration(demo_result, nwb_file):
    result = demo_result["result"]
    with pynwb.NWBHDF5IO(str(nwb_file), "r") as io:
        devices = io.read().devices
        for camera, view in zip(result.cameras, result.cameras.names):
            device = devices[f"camera_{view}"]
            np.testing.assert_allclose(
                device.rotation_matrix[:],
                cv2.Rodrigues(np.asarray(camera.rvec))[0],
                rtol=0,
                atol=1e-12,
            )
            np.testing.assert_array_equal(device.translation_vector[:], camera.tvec)
            fx, fy, cx, cy = camera.intr
            np.testing.assert_array_equal(
                device.intrinsic_matrix[:], [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
            )
            described = json.loads(device.description)
            assert described["rvec"] == list(camera.rvec) and described["image_size_hw"] == [
                480,
                960,
            ]
            # the stored calibration reprojects a world point as OpenCV does with it
            point = np.array([[0.1, -0.2, 0.3]])
            ref, _ = cv2.projectPoints(
                point,
                cv2.Rodrigues(device.rotation_matrix[:])[0],
                device.translation_vector[:],
                device.intrinsic_matrix[:],
                device.distortion_coefficients[:],
            )
            np.testing.assert_allclose(
                ref[:, 0],
                result.cameras.project(point)[list(result.cameras.names).index(view)],
                rtol=0,
                atol=1e-6,
            )


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_nwbinspector_finds_nothing_critical_or_violating(nwb_file):
    from nwbinspector import Importance, inspect_nwbfile

    messages = list(inspect_nwbfile(nwbfile_path=str(nwb_file)))
    bad = [
        m
        for m in messages
        if m.importance in (Importance.CRITICAL, Importance.BEST_PRACTICE_VIOLATION)
    ]
    assert not bad, "\n".join(
        f"{m.importance.name} {m.check_function_name}: {m.message}" for m in bad
    )


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_nwbinspector_flags_a_broken_video_link(demo_result, tmp_path):
    """The inspection above can fail: the inspector checks our video links."""
    from nwbinspector import inspect_nwbfile

    footage = {
        v: [demo_result["recording"] / "gone.mp4"] for v in demo_result["result"].cameras.names
    }
    path = write_nwb(
        demo_result["result"],
        tmp_path / "x.nwb",
        recording_metadata(None, demo_result["recording"]),
        footage=footage,
        frame_rate=FPS,
    )
    messages = list(inspect_nwbfile(nwbfile_path=str(path)))
    assert any(m.check_function_name == "check_image_series_external_file_valid" for m in messages)


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_movement_reads_the_nwb_3d(demo_result, nwb_file):
    from movement.io import load_dataset

    result = demo_result["result"]
    ds = load_dataset(
        nwb_file, source_software="NWB", pose_estimation_key="MultiCameraPoseEstimation"
    )
    assert ds.attrs["fps"] == FPS and ds.attrs["source_software"] == "flylib"
    for p, name in enumerate(result.skeleton.point_names):
        got = ds.position.sel(keypoints=name, individuals=ds.individuals[0]).values  # (time, space)
        np.testing.assert_array_equal(got, result.pts3d[:, p])


def test_confidence_formula_on_hand_made_errors():
    # views x frames x points: 3 views 0 px; 2 views 0 px; 3 views 5 px; 1 view; not reconstructed
    err = np.full((4, 1, 5), np.nan)
    err[:3, 0, 0] = 0.0
    err[:2, 0, 1] = 0.0
    err[:3, 0, 2] = [4.0, 5.0, 6.0]
    err[0, 0, 3] = 0.0
    pts3d = np.zeros((1, 5, 3))
    pts3d[0, 4] = np.nan
    got = confidence_3d(err, pts3d)[0]
    np.testing.assert_allclose(got[:4], [1.0, 0.5, np.exp(-1.0), 0.0], rtol=0, atol=1e-15)
    assert np.isnan(got[4])


def test_a_result_without_confidences_or_errors_still_exports(tmp_path):
    """Only what the result has is written: no 2D confidence, no 3D confidence, no error series."""
    from flylib.camera.rig import CameraGroup
    from flylib.skeleton import Skeleton

    skeleton = Skeleton(
        point_names=("p0", "p1"), limbs={"leg": ("p0", "p1")}, palette={}, name="tiny"
    )
    cameras = CameraGroup.from_arrays(
        ["a", "b"],
        np.zeros((2, 3)),
        np.tile([0.0, 0.0, 20.0], (2, 1)),
        np.tile([800.0, 800.0, 320.0, 240.0], (2, 1)),
        np.zeros((2, 5)),
    )
    pts3d = np.random.default_rng(1).normal(size=(6, 2, 3))
    pts3d[2, 1] = np.nan
    result = PoseResult(
        cameras=cameras, skeleton=skeleton, pts2d=cameras.project(pts3d), pts3d=pts3d
    )
    path = write_nwb(result, tmp_path / "tiny.nwb", DEMO_METADATA, frame_rate=30.0)
    with pynwb.NWBHDF5IO(str(path), "r") as io:
        behavior = io.read().processing["behavior"]
        multi = behavior["MultiCameraPoseEstimation"]
        np.testing.assert_array_equal(_stack(multi, ["p0", "p1"]), pts3d)
        assert multi.pose_estimation_series["p0"].confidence is None
        assert (
            multi.pose_estimations["PoseEstimation_b"].pose_estimation_series["p1"].confidence
            is None
        )
        assert not any(name.startswith("ReprojectionError") for name in behavior.data_interfaces)
        assert multi.pose_estimations["PoseEstimation_a"].source_video is None


# -- session metadata -------------------------------------------------------------------


def test_missing_metadata_is_one_error_naming_every_key_before_reading_results(tmp_path):
    recording = tmp_path / "fly1"
    recording.mkdir()
    table = {"experimenter": "Doe, Jane", "subject": {"sex": "F"}}
    with pytest.raises(ConfigError) as err:
        recording_metadata(table, recording)
    message = str(err.value)
    assert "\n" not in message and str(recording / SIDECAR) in message
    for key in ("session_start_time", "subject.subject_id", "subject.age or subject.date_of_birth"):
        assert key in message
    assert "experimenter" not in message.split("needs:")[1] and "subject.sex" not in message
    # the export checks the metadata before it opens the (here missing) results file
    with pytest.raises(ConfigError, match="session_start_time"):
        run_export_nwb(
            NwbExportInputs.from_config(Config.default()),
            tmp_path / "missing_results.h5",
            tmp_path / "x.nwb",
            recording_dir=recording,
        )


def test_sidecar_overrides_the_config_table_and_bad_entries_name_the_file(tmp_path):
    recording = tmp_path / "fly2"
    recording.mkdir()
    table = {
        "lab": "Fly lab",
        "experimenter": ["Doe, Jane"],
        "subject": {"subject_id": "batch", "sex": "F", "age": "P3D"},
    }
    (recording / SIDECAR).write_text(
        yaml.safe_dump(
            {"session_start_time": "2024-05-01T14:03:00+02:00", "subject": {"subject_id": "fly2"}}
        )
    )
    metadata = recording_metadata(table, recording)
    assert metadata["lab"] == "Fly lab" and metadata["subject"] == {
        "species": "Drosophila melanogaster",
        "subject_id": "fly2",
        "sex": "F",
        "age": "P3D",
    }
    (recording / SIDECAR).write_text(
        "session_start_time: 2024-05-01 14:03\nsubject: {sex: female}\n"
    )
    with pytest.raises(ConfigError) as err:
        recording_metadata(table, recording)
    assert str(recording / SIDECAR) in str(err.value) and "subject.sex" in str(err.value)
    assert "timezone" in str(err.value)


def test_config_validation_checks_the_exports_and_nwb_tables():
    data = Config.default().data
    with pytest.raises(ConfigError) as err:
        Config.from_dict(
            {**data, "exports": {"nwb": "yes"}, "nwb": {"subject": {"age": "3 days"}, "colour": 1}}
        )
    for text in (
        "exports.nwb: expected true or false",
        "nwb.subject.age",
        "nwb.colour: unknown key",
    ):
        assert text in str(err.value)
    Config.from_dict(
        {**data, "exports": {"nwb": True}, "nwb": {"world_unit": "millimeters", "frame_rate": 100}}
    )


def test_the_default_configs_commented_exports_and_nwb_example_is_valid():
    """config/config.yaml documents the tables commented out; uncommented they validate."""
    import re

    text = (Path(__file__).resolve().parents[2] / "config" / "config.yaml").read_text()
    block = text[text.index("# exports:") :]
    example = yaml.safe_load(
        "\n".join(line[2:] for line in block.splitlines() if re.match(r"^# (exports|nwb|  )", line))
    )
    assert example["exports"] == {"nwb": True} and example["nwb"]["subject"]["sex"] == "F"
    config = Config.from_dict({**Config.default().data, **example})
    metadata = recording_metadata(config.data["nwb"], None)
    assert metadata["subject"]["species"] == "Drosophila melanogaster"


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_image_sequence_footage_links_every_image_at_the_configured_rate(demo_result, tmp_path):
    result = demo_result["result"]
    footage = {}
    for view in result.cameras.names:
        footage[view] = [
            tmp_path / "frames" / f"{view}_img_{i:03d}.png" for i in range(result.n_frames)
        ]
        for path in footage[view]:
            path.parent.mkdir(exist_ok=True)
            cv2.imwrite(str(path), np.zeros((4, 4), np.uint8))
    metadata = {**recording_metadata(None, demo_result["recording"]), "frame_rate": 50.0}
    path = write_nwb(result, tmp_path / "out" / "seq.nwb", metadata, footage=footage)
    with pynwb.NWBHDF5IO(str(path), "r") as io:
        nwbfile = io.read()
        video = nwbfile.acquisition["video_lf"]
        assert list(video.external_file[:]) == [
            f"../frames/lf_img_{i:03d}.png" for i in range(result.n_frames)
        ]
        assert list(video.starting_frame[:]) == list(range(result.n_frames)) and video.rate == 50.0
        multi = nwbfile.processing["behavior"]["MultiCameraPoseEstimation"]
        assert multi.pose_estimation_series["lf_claw"].rate == 50.0


def test_no_frame_rate_is_a_clear_error(demo_result, tmp_path):
    with pytest.raises(ConfigError, match="nwb.frame_rate"):
        write_nwb(
            demo_result["result"],
            tmp_path / "x.nwb",
            recording_metadata(None, demo_result["recording"]),
        )


# -- the command line ---------------------------------------------------------------------


@pytest.mark.slow  # >15 s on the shared 2-core machine
def test_cli_exports_nwb_in_one_command(demo_result, tmp_path, capsys):
    out = tmp_path / "out" / "fly.nwb"
    override = tmp_path / "meta.yaml"
    override.write_text("session_id: fly-7\nsubject: {age: P7D}\n")
    assert (
        main(
            [
                "export",
                str(demo_result["results"]),
                "--nwb",
                str(out),
                "--nwb-metadata",
                str(override),
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.strip() == str(out)
    with pynwb.NWBHDF5IO(str(out), "r") as io:
        nwbfile = io.read()
        assert nwbfile.session_id == "fly-7" and nwbfile.subject.age == "P7D"
        assert nwbfile.subject.subject_id == "demo-fly"  # from the demo's nwb.yaml
        video = nwbfile.acquisition["video_rh"]
        assert (out.parent / video.external_file[0]).resolve().is_file()


def test_cli_nwb_without_metadata_fails_in_one_line(demo_result, tmp_path, capsys):
    recording = tmp_path / "copy"
    shutil.copytree(
        demo_result["recording"], recording, ignore=shutil.ignore_patterns("flylib_outputs")
    )
    (recording / SIDECAR).unlink()
    code = main(
        [
            "export",
            str(demo_result["results"]),
            "--nwb",
            str(tmp_path / "x.nwb"),
            "--recording",
            str(recording),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err and "session_start_time" in err and str(recording) in err
    assert "flylib export --nwb-metadata FILE" in err  # the command's own way to supply them
    assert not (tmp_path / "x.nwb").exists()


# -- CSVs through movement --------------------------------------------------------------


def test_movement_reads_the_anipose_3d_csv(demo_result, tmp_path):
    from movement.io import load_dataset

    result = demo_result["result"]
    path = tmp_path / "pose3d.csv"
    assert main(["export", str(demo_result["results"]), "--csv3d", str(path)]) == 0
    ds = load_dataset(path, source_software="Anipose")
    table = pd.read_csv(path)
    for p, name in enumerate(result.skeleton.point_names):
        got = ds.position.sel(keypoints=name).values[:, :, 0]
        np.testing.assert_array_equal(got, result.pts3d[:, p])
        np.testing.assert_array_equal(
            ds.confidence.sel(keypoints=name).values[:, 0], table[f"{name}_score"]
        )


def test_movement_reads_the_dlc_csvs(demo_result, tmp_path):
    from movement.io import load_dataset

    result = demo_result["result"]
    names = list(result.skeleton.point_names)
    files = write_dlc_views(tmp_path, result.pts2d, result.conf, list(result.cameras.names), names)
    for v, path in enumerate(files):
        ds = load_dataset(path, source_software="DeepLabCut")
        for p, name in enumerate(names):
            got = ds.position.sel(keypoints=name).values[:, :, 0]
            np.testing.assert_allclose(got, result.pts2d[v, :, p], rtol=0, atol=1e-9)
            # a point without x/y has no likelihood either (issue 36)
            present = np.isfinite(result.pts2d[v, :, p]).all(-1)
            np.testing.assert_allclose(
                ds.confidence.sel(keypoints=name).values[:, 0],
                np.where(present, result.conf[v, :, p], np.nan),
                rtol=0,
                atol=1e-9,
            )


def test_anipose_layout_exactly():
    pts3d = np.arange(4 * 2 * 3, dtype=float).reshape(4, 2, 3)
    pts3d[1, 0] = np.nan
    err = np.full((3, 4, 2), np.nan)
    err[0], err[1] = 1.0, 3.0
    err[:, 2, 1] = [1.0, np.nan, np.nan]  # b rests on one view in frame 2
    pts2d = np.where(np.isfinite(err)[..., None], 5.0, np.nan)
    conf = np.stack([np.full((4, 2), 0.9), np.full((4, 2), 0.6), np.full((4, 2), 0.1)])
    table = points3d_table(pts3d, ["a", "b"], err, pts2d, conf)
    assert list(table.columns) == [
        "a_x",
        "a_y",
        "a_z",
        "a_error",
        "a_ncams",
        "a_score",
        "b_x",
        "b_y",
        "b_z",
        "b_error",
        "b_ncams",
        "b_score",
        "M_00",
        "M_01",
        "M_02",
        "M_10",
        "M_11",
        "M_12",
        "M_20",
        "M_21",
        "M_22",
        "center_0",
        "center_1",
        "center_2",
        "fnum",
    ]
    assert table["fnum"].tolist() == [0, 1, 2, 3]
    np.testing.assert_array_equal(
        table[[f"M_{i}{j}" for i in range(3) for j in range(3)]].to_numpy(),
        np.tile(np.eye(3).ravel(), (4, 1)),
    )
    assert (table[["center_0", "center_1", "center_2"]] == 0).all().all()
    assert (
        table.loc[0, "a_error"] == 2.0
        and table.loc[0, "a_ncams"] == 2
        and table.loc[0, "a_score"] == 0.6
    )
    assert table.loc[1, ["a_x", "a_y", "a_z", "a_error", "a_score"]].isna().all()
    assert (
        table.loc[2, ["b_error", "b_ncams", "b_score"]].isna().all()
    )  # under two views, as Anipose
    np.testing.assert_array_equal(table[["b_x", "b_y", "b_z"]].to_numpy(), pts3d[:, 1])


def test_anipose_csv_reads_with_anipose_own_reader_logic(tmp_path):
    """What Anipose's filter_3d / label_3d do with a pose-3d CSV: the body parts are the
    ``_error`` columns' prefixes, the points ``<bp>_x/_y/_z``, the alignment ``M_ij``/``center_i``."""
    pts3d = np.random.default_rng(0).normal(size=(5, 3, 3))
    err = np.ones((2, 5, 3))
    path = write_points3d_csv(tmp_path / "p.csv", pts3d, ["l_claw", "r_claw", "head"], err)
    data = pd.read_csv(path)
    bodyparts = [c.replace("_error", "") for c in data.columns if c.endswith("_error")]
    assert bodyparts == ["l_claw", "r_claw", "head"]
    points = np.stack(
        [np.array(data.loc[:, (bp + "_x", bp + "_y", bp + "_z")]) for bp in bodyparts], 1
    )
    rotation = np.array([[data.loc[0, f"M_{i}{j}"] for j in range(3)] for i in range(3)])
    center = np.array([data.loc[0, f"center_{i}"] for i in range(3)])
    np.testing.assert_array_equal((points + center).dot(np.linalg.inv(rotation.T)), pts3d)


# -- the workflow rule ----------------------------------------------------------------------


def _workflow_config(tmp_path):
    from tests.workflow.test_workflow import base_config, make_recording

    config = base_config()
    config["pipeline"]["do_bundle_adjustment"] = False
    config["pipeline"]["do_visualization"] = False
    config["recordings"] = [make_recording(config, tmp_path / "recA", seed=0)]
    config["exports"] = {"nwb": True}
    config["nwb"] = {
        "experimenter": ["Doe, Jane"],
        "lab": "Fly lab",
        "subject": {"sex": "F", "age": "P3D"},
    }
    (tmp_path / "recA" / SIDECAR).write_text(
        "session_start_time: '2024-05-01T14:03:00+02:00'\nsubject: {subject_id: recA}\n"
    )
    return config


@pytest.mark.slow
def test_export_rule_reruns_only_when_the_result_or_its_tables_change(tmp_path):
    import copy

    from tests.workflow.test_workflow import jobs, planned, snakemake

    config = _workflow_config(tmp_path)
    snakemake(tmp_path, config=config)
    nwb = tmp_path / "recA" / "flylib_outputs" / "results.nwb"
    with pynwb.NWBHDF5IO(str(nwb), "r") as io:
        nwbfile = io.read()
        assert nwbfile.subject.subject_id == "recA" and nwbfile.lab == "Fly lab"
        result = PoseResult.load(nwb.with_name("results.h5"))
        multi = nwbfile.processing["behavior"]["MultiCameraPoseEstimation"]
        np.testing.assert_array_equal(_stack(multi, result.skeleton.point_names), result.pts3d)
    assert planned(tmp_path, config) == set()

    edited = copy.deepcopy(config)
    edited["nwb"]["lab"] = "Another lab"
    assert planned(tmp_path, edited) == {("export_nwb", "recA")}
    edited = copy.deepcopy(config)
    edited["pose2d"]["batch_size"] = 3  # performance knob: nothing
    assert planned(tmp_path, edited) == set()
    edited = copy.deepcopy(config)
    edited["triangulation"]["ransac_threshold"] = 9.5
    assert planned(tmp_path, edited) == jobs(
        ("triangulation", "refinement", "assemble", "kinematics", "export_nwb"), ("recA",)
    )
    edited = copy.deepcopy(config)
    edited["exports"]["nwb"] = False
    assert planned(tmp_path, edited) == set()

    sidecar = tmp_path / "recA" / SIDECAR
    sidecar.write_text(sidecar.read_text().replace("recA", "fly-A"))  # the lab edits nwb.yaml
    assert planned(tmp_path, config) == {("export_nwb", "recA")}


@pytest.mark.slow
def test_missing_metadata_stops_the_workflow_before_any_job(tmp_path):
    from tests.workflow.test_workflow import snakemake

    config = _workflow_config(tmp_path)
    del config["nwb"]["experimenter"]
    (tmp_path / "recA" / SIDECAR).unlink()
    proc = snakemake(tmp_path, "--dry-run", config=config, check=False)
    assert proc.returncode != 0
    text = proc.stdout + proc.stderr
    assert "exports.nwb is on" in text and str(tmp_path / "recA" / SIDECAR) in text
    for key in ("session_start_time", "experimenter", "subject.subject_id"):
        assert key in text
    assert "rule pose2d" not in text


@pytest.mark.slow
def test_demo_needs_no_metadata_to_plan_its_export(tmp_path):
    from tests.workflow.test_workflow import base_config, planned

    config = base_config()  # the embedded demo, not generated yet
    config["exports"] = {"nwb": True}
    assert ("export_nwb", "demo") in planned(tmp_path, config)


def test_the_export_job_reads_the_session_metadata_its_rule_tracks(tmp_path):
    """The export rule's params are the exports and nwb tables as JSON (YAML's
    date-times as text); the job rebuilt from them gets the same session metadata as
    the config's own tables."""
    from datetime import timedelta, timezone

    from flylib.pipeline.export_nwb import session_metadata

    data = copy.deepcopy(Config.default().data)
    data["exports"] = {"nwb": True}
    data["nwb"] = {
        "session_start_time": datetime(2024, 5, 1, 14, 3, 7, 250, timezone(timedelta(hours=2))),
        "experimenter": ["Doe, Jane"],
        "subject": {"subject_id": "fly7", "sex": "F", "age": "P3D"},
    }
    inputs = NwbExportInputs.from_config(Config.from_dict(data))
    tracked = inputs.rule_params()
    assert tracked == json.dumps(
        {"exports": data["exports"], "nwb": data["nwb"]}, sort_keys=True, default=str
    )
    rebuilt = NwbExportInputs.from_params(json.loads(tracked), inputs.runtime)
    assert rebuilt.runtime.config_text == Config.from_dict(data).snapshot_text()
    recording = tmp_path / "fly7"
    recording.mkdir()
    from flylib.config.nwb_metadata import parse_datetime

    job, direct = session_metadata(rebuilt, recording), session_metadata(inputs, recording)
    start = data["nwb"]["session_start_time"]
    assert parse_datetime(job.pop("session_start_time"), "job") == start
    assert parse_datetime(direct.pop("session_start_time"), "direct") == start
    assert job == direct
