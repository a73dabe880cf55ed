"""The corrections sidecar: format, edit semantics, and how the triangulation stage applies it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from flylib.config import Config
from flylib.corrections import Corrections, corrections_path
from flylib.errors import ConfigError, ResultsError
from flylib.pipeline.assemble import run_assemble
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.planning import config_rig
from flylib.pipeline.stage_helpers import run_inputs
from flylib.pipeline.triangulation import (
    TriangulationInputs,
    compute_triangulation,
    run_triangulation,
)
from flylib.results import Pose2dData, PoseResult, read_stage
from flylib.triangulation import reconstruct

from gui_fixtures import make_demo_outputs, write_seed_sidecar

FRAMES = 10


@pytest.fixture(scope="module")
def outdir(tmp_path_factory):
    return make_demo_outputs(tmp_path_factory.mktemp("corr") / "rec", frames=FRAMES)


def test_edit_semantics_follow_the_seed_gui():
    c = Corrections.empty(3, 4, 5)
    c.set_invisible(1, 2, 3)
    c.set_point(1, 2, 3, (10.0, 20.0), fixed=True)
    assert c.edited[1, 2, 3] and c.fixed[1, 2, 3] and not c.invisible[1, 2, 3]
    c.set_invisible(1, 2, 3)
    assert c.invisible[1, 2, 3] and not c.edited[1, 2, 3] and not c.fixed[1, 2, 3]
    assert np.isnan(c.points[1, 2, 3]).all()
    c.set_point(0, 2, 1, (1.0, 2.0))
    c.set_point3d(2, 1, (0.0, 0.0, 1.0))
    c.reset(2, point=1, view=0)
    assert not c.edited.any() and c.edited3d[2, 1]  # one view's reset keeps the 3D edit
    c.reset(2)
    assert c.count() == 0


def test_save_writes_the_documented_layout(tmp_path):
    c = Corrections.empty(2, 3, 4, source="x/results.h5")
    c.set_point(1, 2, 3, (5.5, 6.5))
    c.set_invisible(0, 1, 0)
    path = c.save(tmp_path / "corrections.h5")
    with h5py.File(path) as f:
        import json

        meta = json.loads(f.attrs["meta"])
        assert (
            meta["deeperfly_corrections_format_version"] == 3 and meta["source"] == "x/results.h5"
        )
        assert "created_utc" in meta
        g = f["pose2d_corrections"]
        assert g["points"].dtype == np.float64 and g["points"].shape == (2, 3, 4, 2)
        for name in ("edited", "fixed", "invisible"):
            assert g[name].dtype == bool and g[name].shape == (2, 3, 4)
        assert f["pose3d_corrections/points3d"].shape == (3, 4, 3)
        assert f["pose3d_corrections/edited"].dtype == bool
    back = Corrections.load(path, (2, 3, 4))
    np.testing.assert_array_equal(back.points, c.points)
    assert back.invisible[0, 1, 0] and back.edited[1, 2, 3]


def test_review_marks_ride_in_the_sidecar_beside_the_seed_layout(tmp_path):
    """``flylib gui``'s reviewed / OK marks: their own group, the format still version 3
    and every group the seed's reader reads unchanged; a seed file loads with none."""
    c = Corrections.empty(2, 3, 4)
    c.set_point(1, 2, 3, (5.5, 6.5))
    c.reviewed[1, 2] = True
    path = c.save(tmp_path / "corrections.h5")
    with h5py.File(path) as f:
        import json

        assert json.loads(f.attrs["meta"])["deeperfly_corrections_format_version"] == 3
        assert set(f) == {"pose2d_corrections", "pose3d_corrections", "flylib_review"}
        assert f["flylib_review/reviewed"].dtype == bool
        assert f["flylib_review/reviewed"].shape == (3, 4)
    back = Corrections.load(path, (2, 3, 4))
    assert back.reviewed.sum() == 1 and back.reviewed[1, 2]
    assert back.count() == 1  # a mark is not an edit
    seed = write_seed_sidecar(tmp_path / "seed.h5", (2, 3, 4), edits2d=[(0, 1, 2, 3.0, 4.0)])
    assert not Corrections.load(seed, (2, 3, 4)).reviewed.any()
    with h5py.File(seed, "a") as f:
        f["flylib_review/reviewed"] = np.zeros((3, 5), bool)
    with pytest.raises(ResultsError, match=r"its flylib_review/reviewed is \(3, 5\), not the"):
        Corrections.load(seed, (2, 3, 4))


def test_a_newer_or_foreign_file_is_one_clear_error(tmp_path):
    path = write_seed_sidecar(tmp_path / "corrections.h5", (2, 3, 4), version=4)
    with pytest.raises(ResultsError, match="corrections format version 4"):
        Corrections.load(path)
    with h5py.File(path, "w") as f:
        f["x"] = 1
    with pytest.raises(ResultsError, match="not a corrections sidecar"):
        Corrections.load(path)


def test_triangulation_applies_a_seed_layout_sidecar(outdir, tmp_path):
    config = Config.from_file(outdir / "config.yaml")
    pose2d = Pose2dData.load(outdir / "stages" / "pose2d.h5")
    result = PoseResult.load(outdir / "results.h5")
    cameras = result.cameras
    seen = np.isfinite(pose2d.pts2d).all(-1)
    t, p = 4, int(np.flatnonzero(seen[:, 4].sum(axis=0) >= 3)[0])
    views = np.flatnonzero(seen[:, t, p])
    moved = pose2d.pts2d[views[0], t, p] + [6.0, -3.0]
    q = int(np.flatnonzero(seen[:, 6].sum(axis=0) >= 3)[1])
    hidden = int(np.flatnonzero(seen[:, 6, q])[0])
    sidecar = write_seed_sidecar(
        tmp_path / "corrections.h5",
        seen.shape,
        version=3,
        edits2d=[(views[0], t, p, *moved)],
        invisible=[(hidden, 6, q)],
        edits3d=[(8, 0, 0.1, 0.2, 0.3)],
    )
    out = tmp_path / "triangulation.h5"
    run_triangulation(
        run_inputs(config, "triangulation"),
        outdir / "stages" / "pose2d.h5",
        out,
        corrections_path=sidecar,
    )
    tri = read_stage(out, "triangulation")
    expected = pose2d.pts2d.copy()
    expected[views[0], t, p] = moved
    expected[hidden, 6, q] = np.nan
    want3d, _, _ = reconstruct(cameras, expected, config.triangulation, pose2d.conf)
    np.testing.assert_allclose(tri["points3d"][t, p], want3d[t, p], atol=1e-9)
    np.testing.assert_allclose(tri["points3d"][6, q], want3d[6, q], atol=1e-9)
    assert not np.isfinite(tri["points"][hidden, 6, q]).any()
    np.testing.assert_allclose(tri["points3d"][8, 0], [0.1, 0.2, 0.3])
    corrected = tri["corrected"]
    assert corrected.dtype == bool and corrected.sum() == 3 and corrected[t, p] and corrected[6, q]
    assert tri["corrected_2d"].sum() == 2 and tri["attrs"]["corrections"]["count"] == 3
    # untouched points are what the uncorrected run gave
    untouched = ~corrected
    np.testing.assert_array_equal(
        np.isfinite(tri["points3d"][untouched]), np.isfinite(result.pts3d[untouched])
    )
    # assembled: the marks travel into results.h5
    run_assemble(
        stage_inputs(config, "assemble"),
        {"pose2d": outdir / "stages" / "pose2d.h5", "triangulation": out},
        tmp_path / "assembled",
    )
    with h5py.File(tmp_path / "assembled" / "results.h5") as f:
        assert f["triangulation/corrected"][()].sum() == 3


def test_a_fixed_view_stays_in_the_solution(outdir):
    config = Config.from_file(outdir / "config.yaml")
    pose2d = Pose2dData.load(outdir / "stages" / "pose2d.h5")
    cameras = PoseResult.load(outdir / "results.h5").cameras
    inputs = TriangulationInputs.from_config(config)
    seen = np.isfinite(pose2d.pts2d).all(-1)
    t = 2

    def dropped_case():
        # an edit the robust fit rejects: 60 px off, across the epipolar lines of the others
        for p in np.flatnonzero(seen[:, t].sum(axis=0) >= 3):
            for v in np.flatnonzero(seen[:, t, p]):
                for shift in ([60.0, 0.0], [0.0, 60.0]):
                    pts = pose2d.pts2d[:, [t]][:, :, [p]]
                    far = pts[v, 0, 0] + shift
                    plain = Corrections.empty(len(cameras), 1, 1)
                    plain.set_point(v, 0, 0, far)
                    clean = compute_triangulation(inputs, cameras, pts, None, plain).points
                    if not np.isfinite(clean[v, 0, 0]).all():
                        return pts, v, far
        raise AssertionError("no edit was rejected by ransac")

    pts, v, far = dropped_case()
    fixed = Corrections.empty(len(cameras), 1, 1)
    fixed.set_point(v, 0, 0, far, fixed=True)
    solved = compute_triangulation(inputs, cameras, pts, None, fixed)
    np.testing.assert_allclose(solved.points[v, 0, 0], far)
    assert solved.corrected[0, 0] and np.isfinite(solved.points3d).all()
    assert solved.reproj_error[v, 0, 0] < 60


def test_a_sidecar_of_another_shape_fails_naming_it(outdir, tmp_path):
    config = Config.from_file(outdir / "config.yaml")
    sidecar = write_seed_sidecar(tmp_path / "corrections.h5", (7, FRAMES + 2, 38))
    with pytest.raises(ResultsError, match=r"corrections\.h5: corrects a result of"):
        run_triangulation(
            run_inputs(config, "triangulation"),
            outdir / "stages" / "pose2d.h5",
            tmp_path / "t.h5",
            corrections_path=sidecar,
        )
    assert not (tmp_path / "t.h5").exists()


def test_corrections_path_default_and_template(tmp_path):
    config = Config.default()
    assert corrections_path(config.data.get("corrections"), tmp_path) == (
        tmp_path / "corrections.h5",
        False,
    )
    data = dict(config.data, corrections="fixes/{name}.h5")
    assert corrections_path(data["corrections"], tmp_path / "out", tmp_path / "fly1") == (
        tmp_path / "out" / "fixes" / "fly1.h5",
        True,
    )
    with pytest.raises(ConfigError, match=r"corrections: \{nope\} in .* is not a placeholder"):
        corrections_path("{nope}.h5", tmp_path)
    with pytest.raises(ConfigError, match=r"corrections: \{id!r\} in '\{id!r\}.h5' is not"):
        corrections_path("{id!r}.h5", tmp_path)
    from flylib.config.validation import validate_config

    assert not [m for m in validate_config(data) if "corrections" in m]
    assert any("corrections" in m for m in validate_config(dict(config.data, corrections=3)))


def test_corrected_points_are_ringed_in_the_videos():
    from flylib.visualization.draw import draw_rings

    img = np.zeros((60, 60, 3), np.uint8)
    xy = np.array([[30.0, 30.0], [10.0, 10.0], [np.nan, np.nan]])
    draw_rings(img, xy, np.array([True, False, True]), radius=3)
    assert img[30, 30].max() == 0 and img[30, 30 + 7].max() > 100  # a ring, not a disc
    assert img[:20, :20].max() == 0  # not corrected: no ring


def test_the_corrected_triangulation_takes_the_rig_first():
    config = Config.default()
    cameras = config_rig(config, image_sizes={name: (480, 960) for name in config.view_names()})
    pts = np.full((len(cameras.names), 1, 2, 2), np.nan)
    with pytest.raises(TypeError, match="takes the camera rig first"):
        compute_triangulation(TriangulationInputs.from_config(config), pts, cameras)


# -- integrity --------------------------------------------------------------------------


def _flip_a_byte_of(path, dataset):
    """Flip one byte inside ``dataset``'s stored chunk (as bit rot or a bad copy would)."""
    with h5py.File(path, "r") as f:
        info = f[dataset].id.get_chunk_info(0)
    with open(path, "r+b") as raw:
        raw.seek(info.byte_offset + 8)
        byte = raw.read(1)
        raw.seek(info.byte_offset + 8)
        raw.write(bytes([byte[0] ^ 0x40]))


def test_flylib_writes_every_dataset_fletcher32_checksummed(tmp_path):
    from flylib.results import verify_file

    c = Corrections.empty(2, 3, 4)
    c.set_point(1, 2, 3, (5.5, 6.5))
    c.revision = 7
    path = c.save(tmp_path / "corrections.h5")
    unchecked = []
    assert verify_file(path, unchecked=unchecked) == [] and unchecked == []
    with h5py.File(path) as f:
        names = []
        f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        assert len(names) == 6 and all(f[n].fletcher32 for n in names)
    assert Corrections.load(path).revision == 7


@pytest.mark.parametrize(
    "dataset",
    ["pose2d_corrections/points", "pose2d_corrections/edited", "pose3d_corrections/points3d"],
)
def test_flipped_bytes_are_one_error_at_load_never_applied(tmp_path, dataset):
    c = Corrections.empty(2, 3, 4)
    c.set_point(1, 2, 3, (5.5, 6.5))
    c.set_point3d(0, 1, (0.1, 0.2, 0.3))
    path = c.save(tmp_path / "corrections.h5")
    _flip_a_byte_of(path, dataset)
    with pytest.raises(ResultsError, match=rf"corrections.h5: dataset {dataset} is damaged") as err:
        Corrections.load(path)
    assert "\n" not in str(err.value) and "nothing was applied" in str(err.value)


def test_infinite_or_out_of_image_edits_are_one_error_at_load(tmp_path):
    shape = (2, 3, 4)
    path = tmp_path / "corrections.h5"
    # written by hand in the seed's layout (no checksums), as a tampered file would be
    write_seed_sidecar(path, shape, edits3d=[(1, 2, np.inf, 0.0, 0.0)])
    with pytest.raises(
        ResultsError, match=r"points3d holds an infinite value at index \(1, 2, 0\)"
    ):
        Corrections.load(path)
    write_seed_sidecar(path, shape, edits2d=[(0, 1, 2, -np.inf, 4.0)])
    with pytest.raises(ResultsError, match="points holds an infinite value"):
        Corrections.load(path)
    write_seed_sidecar(path, shape, edits3d=[(1, 2, np.nan, 0.0, 0.0)])
    with pytest.raises(ResultsError, match="the 3D edit of frame 1, point 2 is not a finite"):
        Corrections.load(path)
    write_seed_sidecar(path, shape, edits2d=[(1, 0, 3, 1e308, 4.0)])
    assert Corrections.load(path).edited[1, 0, 3]  # sizes unknown: accepted as the seed does
    with pytest.raises(
        ResultsError, match=r"view 1, frame 0, point 3 at \(1e\+308, 4\) lies outside the 960x480"
    ):
        Corrections.load(path, shape, [(480, 960), (480, 960)])
    # a deliberate NaN edit (the seed's "remove") is not an error
    write_seed_sidecar(path, shape, edits2d=[(1, 0, 3, np.nan, np.nan)])
    assert Corrections.load(path, shape, [(480, 960), None]).edited[1, 0, 3]
    # and flylib never writes such a file
    bad = Corrections.empty(*shape)
    bad.set_point3d(0, 0, (np.inf, 0.0, 0.0))
    with pytest.raises(ResultsError, match="not saved, points3d holds an infinite"):
        bad.save(tmp_path / "other.h5")
    assert not (tmp_path / "other.h5").exists()


def test_the_triangulation_stage_refuses_an_out_of_image_sidecar(outdir, tmp_path):
    path = write_seed_sidecar(
        tmp_path / "corrections.h5", (7, FRAMES, 38), edits2d=[(0, 1, 2, 1e308, 5.0)]
    )
    with pytest.raises(ResultsError, match="lies outside the 960x480 image; nothing was applied"):
        run_triangulation(
            run_inputs(Config.from_file(outdir / "config.yaml"), "triangulation"),
            outdir / "stages" / "pose2d.h5",
            tmp_path / "triangulation.h5",
            corrections_path=path,
        )
    assert not (tmp_path / "triangulation.h5").exists()


# -- a sidecar from elsewhere cannot reach beyond itself (issue 37, case 16) ---------------


def _replace_dataset(path, name, make):
    with h5py.File(path, "r+") as f:
        group, leaf = f[name.rpartition("/")[0]], name.rpartition("/")[2]
        shape, dtype = f[name].shape, f[name].dtype
        del f[name]
        make(group, leaf, shape, dtype)


def _triangulation_script(outdir, tmp_path, sidecar):
    """``scripts/triangulation.py --corrections``, as the workflow runs it; a hang is a
    timeout, not a stalled suite."""
    repo = Path(__file__).resolve().parents[1]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(repo / "src"), os.environ.get("PYTHONPATH", "")]),
    }
    return subprocess.run(
        [
            sys.executable,
            str(repo / "scripts" / "triangulation.py"),
            "--config",
            str(outdir / "config.yaml"),
            "--pose2d",
            str(outdir / "stages" / "pose2d.h5"),
            "--out",
            str(tmp_path / "triangulation.h5"),
            "--corrections",
            str(sidecar),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=180,
        check=False,
    )


def test_a_sidecar_stored_in_a_fifo_stops_the_triangulation_job_at_once(outdir, tmp_path):
    sidecar = write_seed_sidecar(tmp_path / "corrections.h5", (7, FRAMES, 38))
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)

    def external(group, leaf, shape, dtype):
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        group.create_dataset(leaf, shape=shape, dtype=dtype, external=[(str(fifo), 0, nbytes)])

    _replace_dataset(sidecar, "pose3d_corrections/points3d", external)
    proc = _triangulation_script(outdir, tmp_path, sidecar)
    assert proc.returncode == 1, proc.stderr
    line = proc.stderr.strip()
    assert "\n" not in line and "Traceback" not in line, line
    assert f"{sidecar}: 'pose3d_corrections/points3d' stores its data in the external file" in line
    assert "save the corrections again from `flylib gui`" in line
    assert not (tmp_path / "triangulation.h5").exists()


def _refused_by_job_and_gui(outdir, tmp_path, sidecar, job_message, gui_message):
    """The triangulation job refuses ``sidecar`` (writing nothing) and so does the review
    GUI opening it as the recording's corrections.h5, each with its one line."""
    from flylib.gui import ReviewSession

    with pytest.raises(ResultsError, match=job_message):
        run_triangulation(
            run_inputs(Config.from_file(outdir / "config.yaml"), "triangulation"),
            outdir / "stages" / "pose2d.h5",
            tmp_path / "t.h5",
            corrections_path=sidecar,
        )
    assert not (tmp_path / "t.h5").exists()
    (outdir / "corrections.h5").write_bytes(sidecar.read_bytes())
    try:
        with pytest.raises(ResultsError, match=gui_message):
            ReviewSession(outdir)
    finally:
        (outdir / "corrections.h5").unlink()


def test_a_sidecar_declaring_terabytes_is_one_line_in_job_and_gui(outdir, tmp_path):

    sidecar = write_seed_sidecar(tmp_path / "corrections.h5", (7, FRAMES, 38))

    def bomb(group, leaf, shape, dtype):  # 4.25 TB declared, no chunk written
        group.create_dataset(
            leaf, shape=(7, 10**9, 38, 2), dtype="f8", chunks=(1, 10**4, 38, 2), compression="gzip"
        )

    _replace_dataset(sidecar, "pose2d_corrections/points", bomb)
    assert sidecar.stat().st_size < 1 << 20
    message = (
        rf"^{sidecar}: 'pose2d_corrections/points' declares \(7, 1000000000, 38, 2\) of float64 "
        r"\(3\.87 TiB\), more than the [0-9.]+ MiB a file of its size can hold"
    )
    _refused_by_job_and_gui(
        outdir,
        tmp_path,
        sidecar,
        message,
        message.replace(rf"^{sidecar}", f"^{outdir}/corrections.h5"),
    )


def test_a_3d_edit_far_outside_the_rig_is_refused_by_job_and_gui(outdir, tmp_path):
    """A 3D edit of 1e300 is finite, but no place on a fly the cameras see: it would
    flow into kinematics and summaries (and overflow there)."""

    sidecar = write_seed_sidecar(
        tmp_path / "corrections.h5", (7, FRAMES, 38), edits3d=[(1, 2, 1e300, 0.0, 0.0)]
    )
    message = (
        r"the 3D edit of frame 1, point 2 at \(1e\+300, 0, 0\) lies 1e\+300 from the cameras, "
        r"more than 1000 x the rig's size \([0-9.]+, the largest distance between two camera "
        r"centres\); nothing was applied"
    )
    _refused_by_job_and_gui(outdir, tmp_path, sidecar, message, message)
    # the bound: 1000 rig sizes from the cameras' mean centre; an edit inside it loads
    cameras = PoseResult.load(outdir / "results.h5").cameras
    centres = cameras.positions
    span = max(np.linalg.norm(a - b) for a in centres for b in centres)
    inside = centres.mean(axis=0) + [999 * span, 0.0, 0.0]
    write_seed_sidecar(sidecar, (7, FRAMES, 38), edits3d=[(1, 2, *inside)])
    assert Corrections.load(sidecar, (7, FRAMES, 38), cameras=cameras).edited3d[1, 2]
    outside = centres.mean(axis=0) + [1001 * span, 0.0, 0.0]
    write_seed_sidecar(sidecar, (7, FRAMES, 38), edits3d=[(1, 2, *outside)])
    with pytest.raises(ResultsError, match="more than 1000 x the rig's size"):
        Corrections.load(sidecar, (7, FRAMES, 38), cameras=cameras)
