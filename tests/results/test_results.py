"""results.h5 schema v2: atomic writes, PoseResult round-trip, stage artifacts, assembly precedence."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

import flylib
from flylib.camera.rig import CameraGroup
from flylib.errors import ResultsError
from flylib.results import (
    FORMAT_VERSION,
    Pose2dData,
    PoseResult,
    assemble_results,
    atomic_path,
    read_cameras,
    read_meta,
    read_skeleton,
    read_stage,
    write_stage,
)
from flylib.skeleton import Skeleton

V, T, P, K = 3, 6, 4, 2
VIEWS = ["a", "b", "c"]


@pytest.fixture(scope="module")
def skeleton() -> Skeleton:
    return Skeleton(
        point_names=("p0", "p1", "p2", "p3"),
        limbs={"leg": ("p1", "p0", "p2"), "tip": ("p3",)},
        palette={"leg": "#112233"},
        name="toy",
    )


def make_rig(offset: float = 0.0, names=VIEWS) -> CameraGroup:
    n = len(names)
    rvecs = np.arange(n * 3, dtype=float).reshape(n, 3) * 0.1 + offset
    tvecs = np.array([[0.0, 0.0, 10.0 + i] for i in range(n)]) + offset
    intrs = np.tile([1000.0, 1001.0, 320.0, 240.0], (n, 1)) + offset
    dists = np.zeros((n, 0)) if offset == 0 else np.full((n, 2), offset * 1e-3)
    return CameraGroup.from_arrays(list(names), rvecs, tvecs, intrs, dists)


def filled(shape, value: float, rng=None) -> np.ndarray:
    """An array of ``value`` plus small noise, with a NaN pattern."""
    rng = rng or np.random.default_rng(0)
    arr = value + rng.normal(scale=0.01, size=shape)
    arr[..., 0, :] = np.nan if arr.ndim > 1 else arr[..., 0, :]
    return arr


def pose2d_data(with_candidates: bool = False) -> Pose2dData:
    rng = np.random.default_rng(1)
    pts2d = rng.uniform(0, 500, size=(V, T, P, 2))
    pts2d[0, :, 3] = np.nan  # view a never sees p3
    pts2d[2, 4] = np.nan
    conf = rng.uniform(size=(V, T, P))
    conf[np.isnan(pts2d[..., 0])] = np.nan
    candidates = None
    if with_candidates:
        from flylib.pictorial import Candidates

        xy = rng.uniform(0, 500, size=(V, T, P, K, 2))
        xy[..., 1, :] = np.nan
        score = rng.uniform(size=(V, T, P, K))
        score[..., 1] = 0.0
        candidates = Candidates(xy=xy, score=score)
    return Pose2dData(pts2d, conf, VIEWS, {v: (480, 960) for v in VIEWS}, candidates)


def assert_rigs_equal(a: CameraGroup, b: CameraGroup) -> None:
    assert list(a.names) == list(b.names)
    for name in ("rvecs", "tvecs", "intrs", "dists"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


# -- atomic writes -----------------------------------------------------------------


def test_atomic_path_renames_on_success(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp != target and not tmp.exists()
        tmp.write_text("done")
        assert not target.exists()
    assert target.read_text() == "done"
    assert [p.name for p in target.parent.iterdir()] == ["out.txt"]


def test_interrupted_write_leaves_no_file_and_no_temporary(tmp_path, skeleton):
    target = tmp_path / "results.h5"
    with pytest.raises(RuntimeError, match="crash"):
        with atomic_path(target) as tmp, h5py.File(tmp, "w") as f:
            f.create_dataset("x", data=np.zeros(10))
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []


def test_interrupted_overwrite_keeps_the_previous_file(tmp_path, skeleton):
    target = tmp_path / "pose2d.h5"
    pose2d_data().save(target, skeleton)
    before = target.read_bytes()

    class FailingScore:  # fails while the file is half written, like a full disk
        shape = (V, T, P, K)

        def __array__(self, dtype=None, copy=None):
            raise OSError("disk full")

    broken = pose2d_data()
    broken.candidates = type(
        "Cand", (), {"xy": np.zeros((V, T, P, K, 2)), "score": FailingScore()}
    )()
    with pytest.raises(OSError, match="disk full"):
        broken.save(target, skeleton)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["pose2d.h5"]


# -- PoseResult ----------------------------------------------------------------------


def test_pose_result_round_trips_with_nan(tmp_path, skeleton):
    data = pose2d_data()
    pts3d = filled((T, P, 3), 1.0)
    reproj = filled((V, T, P), 2.0)
    result = PoseResult(
        make_rig(0.5), skeleton, data.pts2d, data.conf, pts3d, reproj, meta={"fps": 100.0}
    )
    path = tmp_path / "r.h5"
    result.save(path)
    back = PoseResult.load(path)
    np.testing.assert_array_equal(back.pts2d, data.pts2d)  # NaN == NaN here
    np.testing.assert_array_equal(back.conf, data.conf)
    np.testing.assert_array_equal(back.pts3d, pts3d)
    np.testing.assert_array_equal(back.reproj_error, reproj)
    assert np.isnan(back.pts2d[0, :, 3]).all() and np.isnan(back.pts3d[:, 0]).all()
    assert back.pts2d.dtype == np.float64
    assert back.skeleton == skeleton
    assert_rigs_equal(back.cameras, result.cameras)
    assert back.meta["fps"] == 100.0
    assert back.meta["flylib_version"] == flylib.__version__
    assert back.meta["stage"] == "result"
    assert "created_utc" in back.meta
    assert read_meta(path)["deeperfly_format_version"] == FORMAT_VERSION == 2
    assert (back.n_views, back.n_frames, back.n_points) == (V, T, P)


def test_pose_result_without_3d_writes_no_triangulation_group(tmp_path, skeleton):
    data = pose2d_data()
    path = tmp_path / "r.h5"
    PoseResult(make_rig(), skeleton, data.pts2d).save(path)
    with h5py.File(path) as f:
        assert "triangulation" not in f and "conf" not in f["pose2d"]
    back = PoseResult.load(path)
    assert back.pts3d is None and back.conf is None and back.reproj_error is None
    assert back.cameras.dists.shape == (V, 0)


def test_pose_result_checks_shapes(skeleton):
    data = pose2d_data()
    with pytest.raises(ValueError, match=r"pts3d must have shape \(6, 4, 3\)"):
        PoseResult(make_rig(), skeleton, data.pts2d, pts3d=np.zeros((T, P, 2)))
    with pytest.raises(ValueError, match="2 cameras"):
        PoseResult(make_rig(names=["a", "b"]), skeleton, data.pts2d)


def test_wrong_version_is_rejected_naming_the_file(tmp_path, skeleton):
    path = tmp_path / "old.h5"
    PoseResult(make_rig(), skeleton, pose2d_data().pts2d).save(path)
    with h5py.File(path, "a") as f:
        meta = json.loads(f.attrs["meta"])
        meta["deeperfly_format_version"] = 1
        f.attrs["meta"] = json.dumps(meta)
    with pytest.raises(ResultsError, match=r"old\.h5: format version 1, expected 2; re-run"):
        PoseResult.load(path)
    with pytest.raises(ResultsError, match="format version 1"):
        Pose2dData.load(path)


def test_missing_pose2d_group_is_rejected(tmp_path):
    path = tmp_path / "tri.h5"
    write_stage(path, "triangulation", {"points3d": np.zeros((T, P, 3))})
    with pytest.raises(ResultsError, match=r"tri\.h5: has no pose2d group.*re-run"):
        PoseResult.load(path)


def test_missing_or_foreign_files_are_results_errors(tmp_path):
    with pytest.raises(ResultsError, match="nope.h5: no such HDF5 file"):
        PoseResult.load(tmp_path / "nope.h5")
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(ResultsError, match="text.h5: not a readable HDF5 file"):
        PoseResult.load(tmp_path / "text.h5")


def test_large_arrays_are_chunked_and_compressed(tmp_path, skeleton):
    n_frames = 20000
    pts2d = np.full((V, n_frames, P, 2), np.nan)
    pts2d[:, :, :2] = (
        np.round(np.random.default_rng(0).uniform(0, 500, (V, n_frames, 2, 2)) / 7.5) * 7.5
    )
    data = Pose2dData(pts2d, np.ones((V, n_frames, P)), VIEWS, {})
    path = tmp_path / "big.h5"
    data.save(path, skeleton)
    with h5py.File(path) as f:
        points = f["pose2d/points"]
        assert points.compression == "gzip" and points.chunks is not None
        # chunked along time only, about 1 MiB per chunk
        assert points.chunks == (V, 2**20 // (V * P * 2 * 8), P, 2)
    assert path.stat().st_size < pts2d.nbytes / 4
    np.testing.assert_array_equal(Pose2dData.load(path).pts2d, pts2d)


def test_threaded_deflate_writes_standard_gzip_chunks_with_a_padded_edge(tmp_path):
    import zlib

    from flylib.results import fletcher32, write_array

    rng = np.random.default_rng(1)
    arr = rng.normal(size=(3, 50_000))  # 24 bytes per step: two 43,690-column chunks
    arr[:, ::7] = np.nan
    with h5py.File(tmp_path / "a.h5", "w") as f:
        write_array(f, "x", arr)
    with h5py.File(tmp_path / "a.h5") as f:
        ds = f["x"]
        assert ds.compression == "gzip" and ds.compression_opts == 1 and ds.chunks == (3, 43690)
        np.testing.assert_array_equal(ds[()], arr)  # decoded by HDF5's own deflate filter
        np.testing.assert_array_equal(ds[:, 43000:44000], arr[:, 43000:44000])  # across chunks
        assert ds.fletcher32
        mask, raw = ds.id.read_direct_chunk((0, 43690))  # the edge chunk: stored whole
        # deflate stream, then the Fletcher-32 checksum HDF5's filter appends (little-endian)
        assert int.from_bytes(raw[-4:], "little") == fletcher32(raw[:-4])
        edge = np.frombuffer(zlib.decompress(raw[:-4])).reshape(3, 43690)
        assert mask == 0
        np.testing.assert_array_equal(edge[:, : 50_000 - 43690], arr[:, 43690:])
        assert not edge[:, 50_000 - 43690 :].any()


# -- stage artifacts -----------------------------------------------------------------


def test_pose2d_data_round_trips_with_candidates(tmp_path, skeleton):
    data = pose2d_data(with_candidates=True)
    path = tmp_path / "pose2d.h5"
    data.save(path, skeleton)
    back = Pose2dData.load(path)
    np.testing.assert_array_equal(back.pts2d, data.pts2d)
    np.testing.assert_array_equal(back.conf, data.conf)
    assert back.view_names == VIEWS and back.image_sizes == {v: (480, 960) for v in VIEWS}
    from flylib.results import read_image_sizes

    assert read_image_sizes(path) == back.image_sizes  # attributes only, no arrays read
    assert type(back.candidates).__name__ == "Candidates"
    np.testing.assert_array_equal(back.candidates.xy, data.candidates.xy)
    np.testing.assert_array_equal(back.candidates.score, data.candidates.score)
    assert read_skeleton(path) == skeleton
    meta = read_meta(path)
    assert meta["stage"] == "pose2d" and meta["deeperfly_format_version"] == 2
    with h5py.File(path) as f:
        assert "cameras" not in f["pose2d"]  # the rig is not part of detection


def test_candidates_artifact_round_trips_and_names_a_missing_group(tmp_path, skeleton):
    from flylib.results import load_candidates, save_candidates

    cands = pose2d_data(with_candidates=True).candidates
    save_candidates(tmp_path / "candidates.h5", cands)
    back = load_candidates(tmp_path / "candidates.h5")
    np.testing.assert_array_equal(back.xy, cands.xy)
    np.testing.assert_array_equal(back.score, cands.score)
    assert read_meta(tmp_path / "candidates.h5")["stage"] == "candidates"
    pose2d_data().save(tmp_path / "pose2d.h5", skeleton)
    with pytest.raises(
        ResultsError, match=r"pose2d.h5: holds no candidate peaks; re-run the pose2d"
    ):
        load_candidates(tmp_path / "pose2d.h5")


def test_pose2d_data_checks_shapes():
    with pytest.raises(ValueError, match="conf must have shape"):
        Pose2dData(np.zeros((V, T, P, 2)), np.zeros((V, T)), VIEWS, {})
    with pytest.raises(ValueError, match="2 view names for 3 views"):
        Pose2dData(np.zeros((V, T, P, 2)), np.zeros((V, T, P)), VIEWS[:2], {})


def test_write_and_read_stage(tmp_path):
    path = tmp_path / "ba.h5"
    rig = make_rig(0.25)
    summary = {"cost_initial": 12.5, "cost_final": 0.5, "nfev": 40}
    write_stage(path, "bundle_adjustment", {}, cameras=rig, attrs={"summary": summary})
    out = read_stage(path, "bundle_adjustment")
    assert out["attrs"] == {"summary": summary}
    assert_rigs_equal(out["cameras"], rig)
    assert_rigs_equal(read_cameras(path, "bundle_adjustment"), rig)
    with pytest.raises(
        ResultsError, match="has no triangulation group; re-run the triangulation stage"
    ):
        read_stage(path, "triangulation")
    with pytest.raises(ValueError, match="unknown stage 'pose2d'"):
        write_stage(path, "pose2d", {})


# -- assembly ----------------------------------------------------------------------


@pytest.fixture()
def stage_files(tmp_path, skeleton):
    files = {"pose2d": tmp_path / "pose2d.h5"}
    pose2d_data().save(files["pose2d"], skeleton)
    files["bundle_adjustment"] = tmp_path / "ba.h5"
    write_stage(
        files["bundle_adjustment"],
        "bundle_adjustment",
        {},
        cameras=make_rig(0.75),
        attrs={"summary": {"cost": 1.0}},
    )
    for stage, value in (("pictorial_structures", 20.0), ("triangulation", 30.0)):
        files[stage] = tmp_path / f"{stage}.h5"
        write_stage(
            files[stage],
            stage,
            {
                "points": filled((V, T, P, 2), value),
                "points3d": filled((T, P, 3), value + 1),
                "reproj_error": filled((V, T, P), value + 2),
            },
        )
    return files


@pytest.mark.parametrize(
    ("stages", "pts2d_value", "pts3d_value", "rig_offset"),
    [
        (("pose2d",), None, None, 0.0),
        (("pose2d", "bundle_adjustment"), None, None, 0.75),
        (("pose2d", "pictorial_structures"), 20.0, 21.0, 0.0),
        (("pose2d", "triangulation"), 30.0, 31.0, 0.0),
        (
            ("pose2d", "bundle_adjustment", "pictorial_structures", "triangulation"),
            30.0,
            31.0,
            0.75,
        ),
    ],
)
def test_assembly_precedence(
    tmp_path, skeleton, stage_files, stages, pts2d_value, pts3d_value, rig_offset
):
    out = tmp_path / "results.h5"
    config_rig = make_rig(0.0)
    assemble_results(
        out,
        skeleton=skeleton,
        config_rig=config_rig,
        stage_files={s: stage_files[s] for s in stages},
        meta={"recording": "r1"},
        verify=False,  # constant arrays marking which group is read, not a solved pose
    )
    result = PoseResult.load(out)
    reference = pose2d_data()
    np.testing.assert_array_equal(result.conf, reference.conf)  # conf always from pose2d
    if pts2d_value is None:
        np.testing.assert_array_equal(result.pts2d, reference.pts2d)
        assert result.pts3d is None and result.reproj_error is None
    else:
        assert np.nanmean(result.pts2d) == pytest.approx(pts2d_value, abs=0.01)
        assert np.nanmean(result.pts3d) == pytest.approx(pts3d_value, abs=0.01)
        assert np.nanmean(result.reproj_error) == pytest.approx(pts3d_value + 1, abs=0.01)
        assert np.isnan(result.pts3d[:, 0]).all()
    assert_rigs_equal(result.cameras, make_rig(rig_offset))
    assert_rigs_equal(read_cameras(out, "pose2d"), config_rig)
    assert result.image_sizes == {v: (480, 960) for v in VIEWS}
    assert result.skeleton == skeleton
    assert result.meta["stage"] == "assemble" and result.meta["recording"] == "r1"
    assert result.meta["stages"] == list(stages)
    with h5py.File(out) as f:
        assert sorted(k for k in f if k != "skeleton") == sorted(stages)
        assert json.loads(f["pose2d"].attrs["meta"])["stage"] == "pose2d"


def test_assembly_keeps_compression(tmp_path, skeleton):
    n_frames = 4000
    big = Pose2dData(np.full((V, n_frames, P, 2), np.nan), np.zeros((V, n_frames, P)), VIEWS, {})
    big.save(tmp_path / "pose2d.h5", skeleton)
    assemble_results(
        tmp_path / "results.h5",
        skeleton=skeleton,
        config_rig=make_rig(),
        stage_files={"pose2d": tmp_path / "pose2d.h5"},
    )
    with h5py.File(tmp_path / "results.h5") as f:
        assert f["pose2d/points"].compression == "gzip"


def test_assembly_requires_pose2d(tmp_path, skeleton, stage_files):
    with pytest.raises(ResultsError, match="cannot assemble without the pose2d artifact"):
        assemble_results(
            tmp_path / "results.h5",
            skeleton=skeleton,
            config_rig=make_rig(),
            stage_files={"triangulation": stage_files["triangulation"]},
        )
    assert not (tmp_path / "results.h5").exists()


def test_assembly_rejects_a_rig_with_other_views(tmp_path, skeleton, stage_files):
    with pytest.raises(
        ResultsError, match=r"views \['a', 'b', 'c'\] but the rig has cameras \['a', 'c', 'b'\]"
    ):
        assemble_results(
            tmp_path / "results.h5",
            skeleton=skeleton,
            config_rig=make_rig(names=["a", "c", "b"]),
            stage_files={"pose2d": stage_files["pose2d"]},
        )
    assert not (tmp_path / "results.h5").exists()
    assert not any(p.name.startswith(".results.h5") for p in tmp_path.iterdir())


def test_assembly_rejects_another_skeleton(tmp_path, skeleton, stage_files):
    other = Skeleton(point_names=("q0", "q1", "q2", "q3"))
    with pytest.raises(
        ResultsError, match="differ from the config's skeleton; re-run the pose2d stage"
    ):
        assemble_results(
            tmp_path / "results.h5",
            skeleton=other,
            config_rig=make_rig(),
            stage_files={"pose2d": stage_files["pose2d"]},
        )


def test_stage_file_of_wrong_version_stops_assembly(tmp_path, skeleton, stage_files):
    with h5py.File(stage_files["triangulation"], "a") as f:
        f.attrs["meta"] = json.dumps({"deeperfly_format_version": 1})
    with pytest.raises(
        ResultsError, match=r"triangulation\.h5: format version 1.*re-run the triangulation stage"
    ):
        assemble_results(
            tmp_path / "results.h5",
            skeleton=skeleton,
            config_rig=make_rig(),
            stage_files=stage_files,
        )


def test_bare_pose2d_artifact_has_no_rig_for_pose_result(tmp_path, skeleton, stage_files):
    with pytest.raises(ResultsError, match="has no cameras"):
        PoseResult.load(stage_files["pose2d"])


def test_hdf5_file_without_flylib_meta_is_rejected(tmp_path):
    path = tmp_path / "foreign.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("pose2d/points", data=np.zeros((V, T, P, 2)))
    with pytest.raises(ResultsError, match="foreign.h5: not a flylib file"):
        PoseResult.load(path)
    assert read_meta(path) == {}


# -- the package's interface ---------------------------------------------------------------------


def _names_imported_from_results(path) -> set[str]:
    """Names a file imports from ``flylib.results`` (absolute, or relative from inside
    ``src/flylib``), not from its submodules."""
    import ast

    src = Path(flylib.__file__).parent
    package = None
    if src in path.parents:
        package = ".".join(("flylib", *path.relative_to(src).parent.parts))
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.ImportFrom):
            continue
        target = node.module or ""
        if node.level:
            if package is None:
                continue
            base = package.split(".")[: len(package.split(".")) - node.level + 1]
            target = ".".join([*base, *([node.module] if node.module else [])])
        if target == "flylib.results":
            names |= {alias.name for alias in node.names}
    return names


def test_every_name_the_tree_imports_from_flylib_results_is_there():
    import flylib.results

    repo = Path(__file__).resolve().parents[2]
    imported: dict[str, set[str]] = {}
    for folder in ("src", "tests", "scripts", "benchmarks"):
        for path in (repo / folder).rglob("*.py"):
            for name in _names_imported_from_results(path):
                imported.setdefault(name, set()).add(path.name)
    # the split package keeps the single module's names, private helpers other modules use too
    assert {"PoseResult", "open_hdf5", "open_checked", "new_meta", "write_array"} <= set(imported)
    missing = {name: files for name, files in imported.items() if not hasattr(flylib.results, name)}
    assert missing == {}


def test_the_refinement_sink_follows_the_writers_checksum_switch(tmp_path, monkeypatch):
    import h5py

    from flylib.pipeline.refinement import H5Sink
    from flylib.results import datasets

    for switch in (True, False):
        monkeypatch.setattr(datasets, "FLETCHER32", switch)
        with h5py.File(tmp_path / f"{switch}.h5", "w") as f:
            sink = H5Sink(f.create_group("refinement"), 2, 5, 3, chunk=2)
            assert sink.points3d.fletcher32 is switch
            assert sink.flags.fletcher32 is switch


def test_one_opener_raises_the_callers_error_class_naming_file_what_and_fix(tmp_path):
    from flylib.errors import ImportFormatError
    from flylib.results.hdf5 import open_hdf5

    missing, text = tmp_path / "nope.h5", tmp_path / "text.h5"
    text.write_text("not hdf5")
    with pytest.raises(ResultsError) as err:
        open_hdf5(missing, "re-run the workflow")
    assert str(err.value) == f"{missing}: no such HDF5 file; re-run the workflow"
    with pytest.raises(ImportFormatError) as err:
        open_hdf5(text, "check pose2d.import.files", "DeepLabCut .h5", error=ImportFormatError)
    message = str(err.value)
    assert message.startswith(f"{text}: not a readable DeepLabCut .h5 (")
    assert message.endswith("); check pose2d.import.files") and "\n" not in message
    with h5py.File(tmp_path / "ok.h5", "w") as f:
        f.attrs["x"] = 1
    with open_hdf5(tmp_path / "ok.h5", "unused") as f:
        assert f.mode == "r" and f.attrs["x"] == 1
