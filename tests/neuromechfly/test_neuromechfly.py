"""NeuroMechFly joint angles: the model's chains, the template alignment, the IK solver,
the stage's files (flygym's replay layout) and, where flygym installs, the replay."""

from __future__ import annotations

import json
import logging

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from flylib.config import Config
from flylib.errors import ResultsError
from flylib.neuromechfly import compute_nmf_angles, dof_names, forward_kinematics
from flylib.neuromechfly.model import LEGS, leg_lengths
from flylib.pipeline.planning import config_rig

# flygym's own list (flygym.preprogrammed.all_leg_dofs, 1.x and 2.x), written out here
# from its published definition, not from flylib's
FLYGYM_LEG_DOFS = [
    f"joint_{side}{pos}{dof}"
    for side in "LR"
    for pos in "FMH"
    for dof in ["Coxa", "Coxa_roll", "Coxa_yaw", "Femur", "Femur_roll", "Tibia", "Tarsus1"]
]
# a left leg's usual range (radians) in flygym's order; a right leg mirrors roll and yaw
LOW = np.array([-0.5, -1.0, -0.5, -2.5, -1.0, 0.5, -1.5])
HIGH = np.array([1.0, 1.0, 0.5, -0.5, 1.0, 2.5, -0.1])
MIRROR = np.array([1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0])


def _random_angles(n_frames: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    per_leg = rng.uniform(LOW, HIGH, (n_frames, 6, 7))
    per_leg[:, 3:] *= MIRROR
    return per_leg.reshape(n_frames, 42)


def _fly38_from_model(angles: np.ndarray, *, seed: int, noise_mm: float = 0.0) -> np.ndarray:
    """The model's legs for ``angles``, put in a rig-like world: ~110 units from the
    origin, a fly ~6 units long (x2.2 of the model's mm), arbitrarily turned; the
    antennae and abdomen somewhere plausible (not used)."""
    rng = np.random.default_rng(seed)
    legs = forward_kinematics(angles)  # (T, 6, 5, 3) model mm
    legs = legs + rng.normal(0.0, noise_mm, legs.shape)
    skeleton = Config.default().skeleton()
    pts = np.zeros((angles.shape[0], len(skeleton.point_names), 3))
    for k, leg in enumerate(LEGS):
        pts[:, [skeleton.point_names.index(p) for p in skeleton.limbs[f"{leg.lower()}_leg"]]] = (
            legs[:, k]
        )
    for name in skeleton.point_names:
        if "antenna" in name or "abdomen" in name:
            pts[:, skeleton.point_names.index(name)] = rng.normal(0.0, 1.0, 3)
    rotation = Rotation.random(random_state=seed).as_matrix()
    return 2.2 * pts @ rotation.T + np.array([3.0, -2.0, 110.0])


def test_known_angles_on_the_models_chains_come_back_within_one_degree():
    truth = _random_angles(300, seed=1)
    pts3d = _fly38_from_model(truth, seed=2)
    nmf = compute_nmf_angles(pts3d, Config.default().skeleton())
    error = np.degrees(np.abs(np.angle(np.exp(1j * (nmf.angles - truth)))))
    assert not nmf.alignment.mirrored
    assert error.max() < 1.0, f"largest angle error {error.max():.3f} deg"
    assert np.nanmax(nmf.residual) < 0.01


def test_a_mirrored_frame_is_detected_and_gives_the_same_angles(caplog):
    truth = _random_angles(40, seed=3)
    pts3d = _fly38_from_model(truth, seed=4) * np.array([1.0, -1.0, 1.0])
    with caplog.at_level(logging.WARNING):
        nmf = compute_nmf_angles(pts3d, Config.default().skeleton(), source="fly.h5")
    assert nmf.alignment.mirrored
    assert "fly.h5: the legs hang on the dorsal side" in caplog.text
    np.testing.assert_allclose(nmf.angles, truth, atol=np.radians(0.01))


def test_an_untethered_fly_is_refused_with_the_reason():
    truth = _random_angles(50, seed=5)
    pts3d = _fly38_from_model(truth, seed=6)
    pts3d += np.linspace(0.0, 3.0, 50)[:, None, None] * np.array([1.0, 0.0, 0.0])  # walks away
    with pytest.raises(ResultsError, match=r"run\.h5: the thorax is not still .*tethered"):
        compute_nmf_angles(pts3d, Config.default().skeleton(), source="run.h5")


def test_a_leg_with_too_few_points_is_nan_and_named(caplog):
    truth = _random_angles(30, seed=7)
    pts3d = _fly38_from_model(truth, seed=8)
    names = Config.default().skeleton().point_names
    pts3d[:10, names.index("lh_claw")] = np.nan
    pts3d[:, names.index("rm_femur_tibia")] = np.nan
    with caplog.at_level(logging.WARNING):
        nmf = compute_nmf_angles(pts3d, Config.default().skeleton(), source="x.h5")
    columns = {name: k for k, name in enumerate(dof_names())}
    lh = [columns[f"joint_LH{s}"] for s in ("Coxa", "Femur", "Tarsus1")]
    assert np.isnan(nmf.angles[:10, lh]).all() and np.isfinite(nmf.angles[10:, lh]).all()
    assert np.isnan(nmf.angles[:, columns["joint_RMTibia"]]).all()
    assert np.isfinite(nmf.angles[:, columns["joint_LFTibia"]]).all()
    assert nmf.unsolved == {"LH": 10, "RM": 30}
    assert "NeuroMechFly leg LH left NaN in 10 of 30 frames" in caplog.text
    assert "leg RM left NaN in 30 of 30 frames" in caplog.text


def test_too_few_thorax_coxa_points_is_one_line_naming_the_legs():
    pts3d = _fly38_from_model(_random_angles(5, seed=9), seed=9)
    names = Config.default().skeleton().point_names
    for point in ("lf_thorax_coxa", "lm_thorax_coxa", "rh_thorax_coxa"):
        pts3d[:, names.index(point)] = np.nan
    with pytest.raises(ResultsError, match=r"LF, LM, RH never reconstructed"):
        compute_nmf_angles(pts3d, Config.default().skeleton())


def test_forward_kinematics_matches_the_chain_written_out_by_hand():
    # one leg, one pose: rotations composed explicitly with scipy (intrinsic x, y, z)
    angles = np.zeros(42)
    pitch, roll, yaw, ctr_pitch, ctr_roll, fti, tita = 0.3, -0.4, 0.2, -1.2, 0.5, 1.4, -0.6
    angles[:7] = (pitch, roll, yaw, ctr_pitch, ctr_roll, fti, tita)
    from flylib.neuromechfly.model import segment_offsets, thorax_coxa_template

    r1 = Rotation.from_euler("XYZ", [yaw, pitch, roll])
    r2 = r1 * Rotation.from_euler("YZ", [ctr_pitch, ctr_roll])
    r3 = r2 * Rotation.from_euler("Y", fti)
    r4 = r3 * Rotation.from_euler("Y", tita)
    off = segment_offsets()[0]
    expected = [thorax_coxa_template()[0]]
    for rot, o in zip((r1, r2, r3, r4), off):
        expected.append(expected[-1] + rot.apply(o))
    np.testing.assert_allclose(forward_kinematics(angles[None])[0, 0], expected, atol=1e-12)


def test_the_model_is_the_flygym_mjcf_where_flygym_is_installed():
    flygym = pytest.importorskip(
        "flygym",
        reason="flygym is not installed (flygym 2.x needs Python >= 3.12; 1.x pins numpy < 2.1)",
    )
    import xml.etree.ElementTree as ET

    from flylib.neuromechfly.model import segment_offsets, thorax_coxa_template

    path = (
        flygym.util.get_data_path("flygym", "data") / "mjcf" / "neuromechfly_seqik_kinorder_ypr.xml"
    )
    bodies = {b.get("name"): b for b in ET.parse(path).iter("body")}

    def pos(name):
        return np.array([float(v) for v in bodies[name].get("pos").split()])

    for k, leg in enumerate(LEGS):
        np.testing.assert_allclose(thorax_coxa_template()[k], pos(f"{leg}Coxa"), atol=1e-6)
        np.testing.assert_allclose(segment_offsets()[k, 0], pos(f"{leg}Femur"), atol=1e-6)


def test_stage_files_are_flygyms_replay_layout(tmp_path):
    from flylib.neuromechfly.replay import replay_data
    from flylib.pipeline.neuromechfly import angles_figure, write_angles_csv, write_nmf_h5

    truth = _random_angles(25, seed=10)
    nmf = compute_nmf_angles(_fly38_from_model(truth, seed=11), Config.default().skeleton())
    csv = write_angles_csv(tmp_path / "joint_angles.csv", nmf, frame_rate=250.0)
    table = pd.read_csv(csv)
    assert list(table.columns) == ["time", *FLYGYM_LEG_DOFS]
    np.testing.assert_allclose(table["time"], np.arange(25) / 250.0)
    data = replay_data(csv)
    assert data["meta"]["timestep"] == pytest.approx(1 / 250.0)
    np.testing.assert_allclose(
        data["joint_RHTibia"], truth[:, FLYGYM_LEG_DOFS.index("joint_RHTibia")], atol=1e-4
    )

    import h5py

    write_nmf_h5(tmp_path / "neuromechfly.h5", nmf, 250.0)
    with h5py.File(tmp_path / "neuromechfly.h5") as f:
        group = f["neuromechfly"]
        assert group["angles"].shape == (25, 42)
        assert group["residual"].shape == (25, 6, 5)
        assert json.loads(group.attrs["dof_names"]) == FLYGYM_LEG_DOFS
    assert angles_figure(nmf, tmp_path / "a.png", frame_rate=250.0).stat().st_size > 10_000
    bad = tmp_path / "bad.csv"
    bad.write_text("time,joint_LFCoxa\n0,0\n")
    with pytest.raises(ResultsError, match="bad.csv: not a NeuroMechFly angles table"):
        replay_data(bad)


def test_forward_kinematics_residual_on_the_demo_is_reported_and_small(tmp_path, capsys):
    from flylib.pipeline.inputs import stage_inputs
    from flylib.pipeline.neuromechfly import run_neuromechfly

    from gui_fixtures import make_demo_outputs

    out = make_demo_outputs(tmp_path, frames=24)
    data = Config.default().data
    data["pipeline"]["do_neuromechfly"] = True
    inputs = stage_inputs(Config.from_dict(data), "neuromechfly")
    summary = run_neuromechfly(inputs, out / "results.h5", out)
    import h5py

    with h5py.File(out / "neuromechfly.h5") as f:
        per_joint = json.loads(f["neuromechfly"].attrs["residual_summary"])
        model_chain = json.loads(f["neuromechfly"].attrs["model_residual_summary"])
    medians = {k: v["median"] for k, v in per_joint.items()}
    model_medians = [v["median"] for v in model_chain.values()]
    worst = max(medians, key=medians.get)
    print(
        f"demo FK residual: median over joints {np.median(list(medians.values())):.4f}, "
        f"worst joint {worst} {medians[worst]:.4f} leg lengths; on the model's own "
        f"chain: median {np.median(model_medians):.4f}, worst {max(model_medians):.4f}"
    )
    assert summary["frames"] == 24 and sum(summary["unsolved"].values()) <= 2
    assert medians[worst] < 0.05
    assert (out / "joint_angles.png").is_file() and (out / "joint_angles.csv").is_file()


def test_leg_lengths_are_those_of_the_chain():
    zero = forward_kinematics(np.zeros((1, 42)))[0]
    np.testing.assert_allclose(
        np.linalg.norm(np.diff(zero, axis=1), axis=-1).sum(axis=-1), leg_lengths()
    )


def test_flygym_replays_the_angles_and_the_simulated_joints_are_reported(capsys):
    from flylib.neuromechfly.replay import flygym_unavailable, replay_residuals

    reason = flygym_unavailable()
    if reason:
        pytest.skip(reason)
    n_frames = 30
    truth = _random_angles(1, seed=12)
    # a leg swinging gently about one pose, as a tethered fly's legs do
    wave = 0.15 * np.sin(2 * np.pi * 8.0 * np.arange(n_frames) / 100.0)
    angles = truth + wave[:, None]
    nmf = compute_nmf_angles(_fly38_from_model(angles, seed=13), Config.default().skeleton())
    report = replay_residuals(nmf.angles, nmf.aligned, 100.0)
    print(
        f"flygym replay: simulated joints vs measured {report['vs_measured']}, vs model {report['vs_model']}"
    )
    assert report["vs_model"]["median"] < 0.02
    assert report["vs_measured"]["median"] < 0.02


def test_the_angles_go_in_the_nwb_export(tmp_path):
    pynwb = pytest.importorskip("pynwb")
    from flylib.config.nwb_metadata import DEMO_METADATA
    from flylib.interop.nwb import JOINT_ANGLES_NAME, read_joint_angles, write_nwb
    from flylib.pipeline.neuromechfly import write_nmf_h5
    from flylib.results import PoseResult

    config = Config.default()
    truth = _random_angles(12, seed=14)
    pts3d = _fly38_from_model(truth, seed=15)
    pts3d[:3, config.skeleton().point_names.index("rf_claw")] = np.nan
    nmf = compute_nmf_angles(pts3d, config.skeleton())
    write_nmf_h5(tmp_path / "neuromechfly.h5", nmf, 100.0)
    rig = config_rig(config, image_sizes={v: (480, 960) for v in config.view_names()})
    result = PoseResult(
        cameras=rig, skeleton=config.skeleton(), pts2d=np.asarray(rig.project(pts3d)), pts3d=pts3d
    )
    path = write_nwb(
        result,
        tmp_path / "fly.nwb",
        DEMO_METADATA,
        frame_rate=100.0,
        joint_angles=read_joint_angles(tmp_path / "neuromechfly.h5"),
    )
    with pynwb.NWBHDF5IO(str(path), "r") as io:
        series = io.read().processing["behavior"][JOINT_ANGLES_NAME].time_series
        assert sorted(series) == sorted(FLYGYM_LEG_DOFS)
        assert series["joint_LHTibia"].unit == "radians" and series["joint_LHTibia"].rate == 100.0
        np.testing.assert_allclose(
            series["joint_LHTibia"].data[:], truth[:, FLYGYM_LEG_DOFS.index("joint_LHTibia")]
        )
        assert np.isnan(series["joint_RFTarsus1"].data[:3]).all()


def test_the_solver_agrees_with_seqikpy_on_the_same_legs():
    from pathlib import Path

    from flylib.neuromechfly.ik import solve_leg_angles

    ref = np.load(
        Path(__file__).resolve().parents[1] / "data" / "interop" / "seqikpy_1.1.0_front_legs.npz",
        allow_pickle=False,
    )
    legs = np.full((ref["legs"].shape[0], 6, 5, 3), np.nan)
    legs[:, 0], legs[:, 3] = ref["legs"][:, 0], ref["legs"][:, 1]
    straight = np.zeros((6, 4, 3))
    straight[..., 2] = -ref["segment_lengths"]  # SeqIKPy's chains: segments along -z
    ours = solve_leg_angles(legs, offsets=straight)
    for k, leg in ((0, "LF"), (3, "RF")):
        difference = np.degrees(np.abs(np.angle(np.exp(1j * (ours[:, k] - ref[f"seqikpy_{leg}"])))))
        assert difference.max() < 0.01, f"{leg}: {difference.max(axis=0)} deg"
    assert np.isnan(ours[:, [1, 2, 4, 5]]).all()


def test_deepfly3ds_real_3d_aligns_and_fits(capsys):
    """DeepFly3D's own 3D of a real tethered fly (its package example): tethered, in a
    left-handed frame (mirrored first), and the chains fit it (a truth-free measure)."""
    from conftest import shared_subdir

    from flylib.interop.df3d import FLY38_POINT_NAMES, df3d_joint_to_fly38, load_pickle

    path = shared_subdir("deepfly3d-package-example") / "df3d_result.pkl"
    raw = np.asarray(load_pickle(path, "DeepFly3D result")["points3d"], dtype=np.float64)
    pts3d = np.full((raw.shape[0], len(FLY38_POINT_NAMES), 3), np.nan)
    for joint in range(raw.shape[1]):
        pts3d[:, FLY38_POINT_NAMES.index(df3d_joint_to_fly38(joint))] = raw[:, joint]
    nmf = compute_nmf_angles(pts3d, Config.default().skeleton(), source=str(path))
    print(
        f"DeepFly3D example: thorax motion {nmf.alignment.thorax_motion:.4f} leg lengths; FK "
        f"residual median {np.nanmedian(nmf.residual):.4f}, p95 "
        f"{np.nanpercentile(nmf.residual, 95):.4f} (model's chain median "
        f"{np.nanmedian(nmf.model_residual):.4f})"
    )
    assert nmf.alignment.mirrored and not nmf.unsolved
    assert nmf.alignment.thorax_motion < 0.1 / 3  # the default tolerance has a margin
    assert np.nanpercentile(nmf.residual, 95) < 0.05


def test_the_stage_refuses_a_mirror_image_with_the_cause_assemble_stored(tmp_path):
    """Issue 36: the refusal repeats the cause stored in results.h5 (its calibration
    file and the switch), and neuromechfly.allow_mirrored lets the fit run."""
    from flylib.handedness import WORLD_MIRROR, handedness, rig_check
    from flylib.pipeline.inputs import stage_inputs
    from flylib.pipeline.neuromechfly import run_neuromechfly
    from flylib.results import PoseResult

    config = Config.default()
    rig = config_rig(config, image_sizes={v: (480, 960) for v in config.view_names()})
    pts3d = _fly38_from_model(_random_angles(10, seed=1), seed=2) @ WORLD_MIRROR
    entry = rig_check(
        handedness(pts3d, config.skeleton()), rig="the calibration file x/calib.pkl", from_file=True
    )
    path = tmp_path / "results.h5"
    PoseResult(
        cameras=rig,
        skeleton=config.skeleton(),
        pts2d=np.asarray(rig.project(pts3d)),
        pts3d=pts3d,
        meta={"handedness": entry},
    ).save(path)
    with pytest.raises(ResultsError) as info:
        run_neuromechfly(stage_inputs(config, "neuromechfly"), path, tmp_path)
    assert str(info.value) == (
        f"{path}: neuromechfly refused: {entry['message']}. To run neuromechfly on the mirror "
        "image anyway, set neuromechfly: {allow_mirrored: true}"
    )
    data = config.data
    data["neuromechfly"]["allow_mirrored"] = True
    summary = run_neuromechfly(stage_inputs(Config.from_dict(data), "neuromechfly"), path, tmp_path)
    assert summary["frames"] == 10
