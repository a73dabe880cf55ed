"""flylib's own HDF5 files cannot reach beyond themselves (issue 37, case 16).

A results.h5 (or stage artifact) from a collaborator is as untrusted as another tool's
file: each one here is written by flylib and then altered with h5py the way a hostile
file would be -- a dataset's bytes stored in a FIFO or in one of the recipient's files
(HDF5 external storage), an external link, a virtual dataset, or a few KB declaring
terabytes -- and read through the real commands. A read that could hang runs in a
subprocess with a timeout, so a hang fails the test instead of stalling the suite.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from flylib.camera.rig import CameraGroup
from flylib.cli import main
from flylib.errors import ResultsError
from flylib.results import (
    Pose2dData,
    PoseResult,
    load_candidates,
    read_cameras,
    read_stage,
    save_candidates,
    verify_file,
    write_stage,
)
from flylib.results.guard import MAX_EXPANSION, file_budget
from flylib.skeleton import Skeleton

REPO = Path(__file__).resolve().parents[2]
VIEWS = ["a", "b", "c"]
FRAMES, POINTS = 5, 3
#: What the recipient's file holds: values no pose would, found in any CSV that copied them.
SECRET = np.arange(FRAMES * POINTS * 3, dtype=np.float64) + 0.123456789


def _env() -> dict:
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]),
    }


@pytest.fixture
def result(tmp_path) -> PoseResult:
    skeleton = Skeleton(
        point_names=("p0", "p1", "p2"), limbs={"leg": ("p0", "p1", "p2")}, palette={}, name="t"
    )
    cameras = CameraGroup.from_arrays(
        VIEWS,
        np.stack([[0.0, a, 0.0] for a in np.deg2rad([-30.0, 0.0, 30.0])]),
        np.tile([0.0, 0.0, 20.0], (3, 1)),
        np.tile([800.0, 810.0, 320.0, 240.0], (3, 1)),
        np.zeros((3, 5)),
    )
    pts3d = np.random.default_rng(0).normal(size=(FRAMES, POINTS, 3))
    return PoseResult(
        cameras=cameras,
        skeleton=skeleton,
        pts2d=cameras.project(pts3d),
        pts3d=pts3d,
        reproj_error=np.full((3, FRAMES, POINTS), 0.5),
    )


@pytest.fixture
def results(tmp_path, result) -> Path:
    path = tmp_path / "results.h5"
    result.save(path)
    return path


def _replace(path: Path, name: str, make) -> None:
    """Replace dataset ``name`` of ``path`` by what ``make(group, leaf, shape, dtype)`` makes."""
    with h5py.File(path, "r+") as f:
        parent, _, leaf = name.rpartition("/")
        shape, dtype = f[name].shape, f[name].dtype
        del f[name]
        make(f[parent] if parent else f, leaf, shape, dtype)


def _external_storage(target: Path):
    def make(group, leaf, shape, dtype):
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        group.create_dataset(leaf, shape=shape, dtype=dtype, external=[(str(target), 0, nbytes)])

    return make


def _external_link(target: Path):
    def make(group, leaf, shape, dtype):
        with h5py.File(target, "w") as other:
            other["data"] = SECRET.reshape(shape)
        group[leaf] = h5py.ExternalLink(str(target), "/data")

    return make


def _virtual(target: Path):
    def make(group, leaf, shape, dtype):
        with h5py.File(target, "w") as other:
            other["data"] = SECRET.reshape(shape)
        layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
        layout[...] = h5py.VirtualSource(str(target), "data", shape=shape)
        group.create_virtual_dataset(leaf, layout)

    return make


def _bomb(group, leaf, shape, dtype):
    """Terabytes declared by a dataset whose chunks were never written: a few KB on disk."""
    group.create_dataset(
        leaf, shape=(10**8, 3000, 3), dtype="f8", chunks=(1000, 100, 3), compression="gzip"
    )


def _one_line(text: str, path: Path, *fragments: str) -> None:
    text = text.strip()
    assert "\n" not in text and "Traceback" not in text, text
    assert str(path) in text, text
    for fragment in fragments:
        assert fragment in text, text


def _flylib(*args: str) -> subprocess.CompletedProcess:
    """The ``flylib`` console script in a subprocess: a hang is a timeout, not a stall."""
    return subprocess.run(
        [sys.executable, "-m", "flylib.cli", *args],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=120,
        check=False,
    )


# -- the user's commands -----------------------------------------------------------------


def test_inspect_and_export_of_a_result_stored_in_a_fifo_refuse_at_once(results, tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    _replace(results, "triangulation/points3d", _external_storage(fifo))
    csv = tmp_path / "points3d.csv"
    for args in (["inspect", str(results)], ["export", str(results), "--csv3d", str(csv)]):
        proc = _flylib(*args)
        assert proc.returncode == 1, proc.stderr
        _one_line(
            proc.stderr,
            results,
            "'triangulation/points3d' stores its data in the external file",
            str(fifo),
            "never following a link out of it",
        )
    assert not csv.exists()


def test_export_never_copies_another_file_into_the_csv(results, tmp_path, capsys):
    """A collaborator's results.h5 whose 3D points are stored in a file of the recipient's
    (its absolute path): the export would carry that file's bytes into the CSV."""
    secret = tmp_path / "private" / "notes.bin"
    secret.parent.mkdir()
    secret.write_bytes(SECRET.tobytes())
    _replace(results, "triangulation/points3d", _external_storage(secret))
    csv = tmp_path / "points3d.csv"
    assert main(["export", str(results), "--csv3d", str(csv)]) == 1
    _one_line(capsys.readouterr().err, results, f"the external file '{secret}'")
    assert not csv.exists()


def test_a_result_declaring_terabytes_is_refused_before_anything_is_allocated(results, tmp_path):
    _replace(results, "triangulation/points3d", _bomb)
    assert results.stat().st_size < 1 << 20
    for args in (["inspect", str(results)], ["export", str(results), "--csv3d", "x.csv"]):
        proc = _flylib(*args)
        assert proc.returncode == 1, proc.stderr
        _one_line(
            proc.stderr,
            results,
            "'triangulation/points3d' declares (100000000, 3000, 3) of float64 (6.55 TiB)",
            "more than the 64 MiB a file of its size can hold",
        )


# -- every way out of the file, every reader ----------------------------------------------


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (_external_storage, "stores its data in the external file"),
        (_external_link, "is an external link to"),
        (_virtual, "is a virtual dataset mapping"),
    ],
    ids=["external-storage", "external-link", "virtual-dataset"],
)
def test_no_way_out_of_a_results_file_is_followed(results, tmp_path, make, words):
    target = tmp_path / "elsewhere.h5"
    if make is _external_storage:
        target.write_bytes(SECRET.tobytes())
    _replace(results, "triangulation/points3d", make(target))
    with pytest.raises(ResultsError) as err:
        PoseResult.load(results)
    _one_line(str(err.value), results, f"'triangulation/points3d' {words}", "re-run the pipeline")
    assert str(err.value).startswith(f"{results}: ")
    [problem] = verify_file(results)  # what `flylib inspect` checks first
    _one_line(problem, results, words)


def test_a_link_out_deep_inside_a_group_is_found(results, tmp_path):
    """Not only the datasets a reader asks for: a link anywhere in the file."""
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.zeros(3)
    with h5py.File(results, "r+") as f:
        f.create_group("pose2d/cameras/extra")["hidden"] = h5py.ExternalLink(str(other), "/x")
    with pytest.raises(ResultsError, match=r"'pose2d/cameras/extra/hidden' is an external link"):
        read_cameras(results, "pose2d")


def _artifacts(tmp_path: Path, result: PoseResult) -> dict[str, Path]:
    stages = tmp_path / "stages"
    stages.mkdir()
    pose2d = Pose2dData(
        pts2d=result.pts2d,
        conf=np.ones(result.pts2d.shape[:3]),
        view_names=VIEWS,
        image_sizes={v: (480, 640) for v in VIEWS},
    )
    pose2d.save(stages / "pose2d.h5", result.skeleton)
    write_stage(stages / "triangulation.h5", "triangulation", {"points3d": result.pts3d})
    write_stage(stages / "bundle_adjustment.h5", "bundle_adjustment", {}, cameras=result.cameras)
    from flylib.pictorial import Candidates

    xy = np.repeat(result.pts2d[:, :, :, None], 2, axis=3)
    save_candidates(stages / "candidates_k2.h5", Candidates(xy=xy, score=np.ones(xy.shape[:4])))
    return {
        "pose2d/points": stages / "pose2d.h5",
        "triangulation/points3d": stages / "triangulation.h5",
        "bundle_adjustment/cameras/tvecs": stages / "bundle_adjustment.h5",
        "candidates/xy": stages / "candidates_k2.h5",
    }


READERS = {
    "pose2d/points": Pose2dData.load,
    "triangulation/points3d": lambda p: read_stage(p, "triangulation"),
    "bundle_adjustment/cameras/tvecs": lambda p: read_stage(p, "bundle_adjustment"),
    "candidates/xy": load_candidates,
}


@pytest.mark.parametrize("name", list(READERS))
def test_every_stage_artifact_reader_is_guarded(tmp_path, result, name):
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.zeros(10**5).tobytes())
    path = _artifacts(tmp_path, result)[name]
    READERS[name](path)  # as written: loads
    _replace(path, name, _external_storage(secret))
    with pytest.raises(ResultsError) as err:
        READERS[name](path)
    _one_line(str(err.value), path, f"'{name}' stores its data in the external file")


def test_the_budget_follows_the_file_size(tmp_path):
    small = tmp_path / "small.h5"
    small.write_bytes(b"\0" * 1000)
    assert file_budget(small) == 64 << 20
    big = tmp_path / "big.h5"
    with open(big, "wb") as f:
        f.truncate(1 << 20)
    assert file_budget(big) == MAX_EXPANSION << 20


def test_an_intact_long_result_is_read_as_written(tmp_path, result):
    """The guard refuses nothing flylib writes: an all-NaN array compresses ~190x."""
    long = PoseResult(
        cameras=result.cameras,
        skeleton=result.skeleton,
        pts2d=np.full((3, 20_000, POINTS, 2), np.nan),
        pts3d=np.full((20_000, POINTS, 3), np.nan),
    )
    long.save(tmp_path / "results.h5")
    back = PoseResult.load(tmp_path / "results.h5")
    assert back.pts3d.shape == (20_000, POINTS, 3) and np.isnan(back.pts3d).all()
    assert verify_file(tmp_path / "results.h5") == []
