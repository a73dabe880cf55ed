"""Foreign HDF5 inputs cannot reach beyond themselves.

Every file here starts from one made by the other tool (a SLEAP analysis file written
by ``sleap_io``; DeepLabCut's pandas HDF5 files in ``tests/data/interop``) and is then
altered with h5py the way a hostile or careless file would be: its data stored in
another file, linked to another file or to a FIFO, mapped from other files by a
virtual dataset, or declaring far more than it stores (sparse, gzip of zeros).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from flylib.errors import ImportFormatError
from flylib.interop import read_dlc_h5, read_sleap_analysis
from flylib.interop._h5 import DEFAULT_READ_BUDGET, read_budget
from flylib.pipeline.pose2d import import_target

DATA = Path(__file__).resolve().parents[1] / "data" / "interop"
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def sleap_file(tmp_path) -> Path:
    """A one-track SLEAP analysis file of 5 frames x 3 nodes, written by sleap_io."""
    sio = pytest.importorskip("sleap_io")
    skeleton = sio.Skeleton(["head", "thorax", "abdomen"])
    video = sio.Video(filename="camera_0.mp4")
    track = sio.Track("fly")
    frames = [
        sio.LabeledFrame(
            video=video,
            frame_idx=t,
            instances=[
                sio.PredictedInstance.from_numpy(
                    np.array([[10.0 + t, 20.0], [30.0, 40.0], [50.0, 60.0]]),
                    skeleton=skeleton,
                    point_scores=np.array([0.9, 0.8, 0.7]),
                    score=1.0,
                    track=track,
                )
            ],
        )
        for t in range(5)
    ]
    labels = sio.Labels(labeled_frames=frames, videos=[video], skeletons=[skeleton], tracks=[track])
    path = tmp_path / "rh.analysis.h5"
    sio.save_analysis_h5(labels, str(path))
    return path


def _replace(path: Path, name: str, make) -> None:
    with h5py.File(path, "r+") as f:
        del f[name]
        make(f, name)


def _one_line_refusal(load, path: Path, *fragments: str) -> str:
    with pytest.raises(ImportFormatError) as err:
        load(path)
    text = str(err.value)
    assert "\n" not in text and text.startswith(str(path)), text
    for fragment in fragments:
        assert fragment in text, text
    return text


def test_sleap_file_as_written_still_loads(sleap_file):
    kp = read_sleap_analysis(sleap_file)
    assert kp.xy.shape == (5, 3, 2)
    np.testing.assert_array_equal(kp.xy[:, 0, 0], 10.0 + np.arange(5))


def test_sleap_tracks_in_external_storage_are_refused(sleap_file, tmp_path):
    """The probe's case: ``tracks`` stored in /etc/ssl/certs/ca-certificates.crt."""
    outside = tmp_path / "outside.bin"
    outside.write_bytes(np.full(30, 1e175).tobytes())
    _replace(
        sleap_file,
        "tracks",
        lambda f, n: f.create_dataset(
            n, shape=(1, 2, 3, 5), dtype="<f8", external=[(str(outside), 0, 240)]
        ),
    )
    text = _one_line_refusal(
        read_sleap_analysis, sleap_file, "'tracks'", "external file", str(outside)
    )
    assert "never follows a link out of it" in text


def test_sleap_external_link_to_another_h5_is_refused_not_followed(sleap_file, tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["tracks"] = np.full((1, 2, 3, 5), 1e175)
    _replace(
        sleap_file, "tracks", lambda f, n: f.__setitem__(n, h5py.ExternalLink(other, "/tracks"))
    )
    _one_line_refusal(
        read_sleap_analysis, sleap_file, "'tracks' is an external link to", "other.h5"
    )


def test_sleap_soft_link_through_an_external_link_is_refused(sleap_file, tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_group("g")["tracks"] = np.zeros((1, 2, 3, 5))

    def make(f, name):
        f["elsewhere"] = h5py.ExternalLink(other, "/g")
        f[name] = h5py.SoftLink("/elsewhere/tracks")

    _replace(sleap_file, "tracks", make)
    _one_line_refusal(read_sleap_analysis, sleap_file, "'elsewhere' is an external link")


def test_sleap_soft_link_inside_the_file_is_followed(sleap_file):
    def make(f, name):
        f.create_group("kept")["tracks"] = np.zeros((1, 2, 3, 5)) + 7.0
        f[name] = h5py.SoftLink("kept/tracks")  # relative to the root group

    _replace(sleap_file, "tracks", make)
    assert (read_sleap_analysis(sleap_file).xy == 7.0).all()


def test_sleap_soft_link_cycle_is_one_line(sleap_file):
    def make(f, name):
        f["a"] = h5py.SoftLink("/b")
        f["b"] = h5py.SoftLink("/a")
        f[name] = h5py.SoftLink("/a")

    _replace(sleap_file, "tracks", make)
    _one_line_refusal(read_sleap_analysis, sleap_file, "chain of more than 16 soft links")


def test_sleap_virtual_dataset_is_refused(sleap_file, tmp_path):
    other = tmp_path / "source.h5"
    with h5py.File(other, "w") as f:
        f["data"] = np.full((1, 2, 3, 5), 1e175)

    def make(f, name):
        layout = h5py.VirtualLayout(shape=(1, 2, 3, 5), dtype="<f8")
        layout[...] = h5py.VirtualSource(other, "data", shape=(1, 2, 3, 5))
        f.create_virtual_dataset(name, layout)

    _replace(sleap_file, "tracks", make)
    _one_line_refusal(read_sleap_analysis, sleap_file, "'tracks' is a virtual dataset", "source.h5")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs POSIX FIFOs")
def test_sleap_external_link_to_a_fifo_does_not_hang(sleap_file, tmp_path):
    """HDF5 opens an external link's file when the link is followed; a FIFO blocks that
    open forever. The link is refused from the link table, so nothing opens it."""
    fifo = tmp_path / "pipe.h5"
    os.mkfifo(fifo)
    _replace(sleap_file, "tracks", lambda f, n: f.__setitem__(n, h5py.ExternalLink(fifo, "/x")))
    code = textwrap.dedent(
        f"""
        from flylib.errors import ImportFormatError
        from flylib.interop import read_sleap_analysis
        try:
            read_sleap_analysis({str(sleap_file)!r})
        except ImportFormatError as exc:
            print(exc)
        """
    )
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    try:
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env
        )
    except subprocess.TimeoutExpired:
        pytest.fail("reading a SLEAP file whose 'tracks' links to a FIFO hangs")
    assert "'tracks' is an external link to" in done.stdout and "pipe.h5" in done.stdout, (
        done.stdout + done.stderr
    )


def test_sleap_sparse_dataset_declaring_terabytes_is_refused_unread(sleap_file):
    """A few KB on disk, 48 GB declared: refused from its shape, before any allocation."""
    _replace(
        sleap_file,
        "tracks",
        lambda f, n: f.create_dataset(
            n, shape=(1, 2, 3, 10**9), dtype="<f8", chunks=(1, 2, 3, 4096)
        ),
    )
    assert sleap_file.stat().st_size < 1 << 20
    _one_line_refusal(
        read_sleap_analysis, sleap_file, "'tracks' declares (1, 2, 3, 1000000000)", "refusing"
    )


def test_sleap_gzip_of_zeros_beyond_the_recordings_budget_is_refused(sleap_file):
    """16 MiB of zeros compressed to a few KB, read under an 8 MiB budget."""
    frames = (16 << 20) // (2 * 3 * 8)

    def make(f, name):
        f.create_dataset(
            name,
            data=np.zeros((1, 2, 3, frames)),
            chunks=(1, 2, 3, 1 << 16),
            compression="gzip",
            compression_opts=9,
        )

    _replace(sleap_file, "tracks", make)
    assert sleap_file.stat().st_size < 1 << 20
    _one_line_refusal(
        lambda p: read_sleap_analysis(p, max_bytes=8 << 20), sleap_file, "16 MiB", "8 MiB"
    )


def test_a_chunk_larger_than_the_budget_is_refused_even_for_a_small_dataset(sleap_file):
    """Reading any element decompresses its whole chunk: a 15-element dataset whose
    (extendible) chunk holds 1.5 GB is refused too."""
    _replace(
        sleap_file,
        "tracks",
        lambda f, n: f.create_dataset(
            n, shape=(1, 2, 3, 5), maxshape=(1, 2, 3, None), chunks=(1, 2, 3, 1 << 25), dtype="<f8"
        ),
    )
    _one_line_refusal(
        lambda p: read_sleap_analysis(p, max_bytes=64 << 20), sleap_file, "declares chunks of"
    )


def test_read_budget_grows_with_the_recording_and_is_bounded():
    assert read_budget(None, 38) == DEFAULT_READ_BUDGET
    assert read_budget(15, 38) == 64 << 20  # a short recording: the floor
    per_frame = 3 * 64 * 64 * 8
    assert read_budget(100_000, 38) == min(DEFAULT_READ_BUDGET, 100_000 * per_frame)
    assert read_budget(10_000, 38) == 10_000 * per_frame
    assert read_budget(2_000, 200) == 2_000 * 3 * 64 * 200 * 8  # more points, more room
    assert read_budget(10**9, 38) == DEFAULT_READ_BUDGET


@pytest.mark.parametrize("seed", ["dlc_table.h5", "dlc_fixed.h5"])
def test_dlc_h5_value_block_linked_out_of_the_file_is_refused(seed, tmp_path):
    path = tmp_path / seed
    shutil.copy(DATA / seed, path)
    block = "df_with_missing/table" if "table" in seed else "df_with_missing/block0_values"
    other = tmp_path / "other.h5"
    with h5py.File(path) as src, h5py.File(other, "w") as dst:
        dst["copy"] = src[block][()]
    _replace(path, block, lambda f, n: f.__setitem__(n, h5py.ExternalLink(other, "/copy")))
    _one_line_refusal(read_dlc_h5, path, "is an external link to", "other.h5")


def test_dlc_h5_dataframe_group_linked_out_of_the_file_is_refused(tmp_path):
    path = tmp_path / "view.h5"
    shutil.copy(DATA / "dlc_table.h5", path)
    other = tmp_path / "df.h5"
    shutil.copy(DATA / "dlc_table.h5", other)
    _replace(
        path,
        "df_with_missing",
        lambda f, n: f.__setitem__(n, h5py.ExternalLink(other, "/df_with_missing")),
    )
    _one_line_refusal(read_dlc_h5, path, "'df_with_missing' is an external link to")


def test_dlc_h5_sparse_value_block_is_refused(tmp_path):
    path = tmp_path / "view.h5"
    shutil.copy(DATA / "dlc_fixed.h5", path)
    _replace(
        path,
        "df_with_missing/block0_values",
        lambda f, n: f.create_dataset(n, shape=(10**8, 10**4), dtype="<f8", chunks=(64, 64)),
    )
    _one_line_refusal(read_dlc_h5, path, "'df_with_missing/block0_values' declares")


def test_import_budget_comes_from_the_recordings_footage(sleap_file, tmp_path, df3d_sample_dir):
    """The real 15-frame sample's camera_0.mp4 as view rh's footage: a SLEAP file for rh
    declaring 10 million frames (480 MB, sparse) is under the 2 GiB default but far over
    what 15 frames can need (the 64 MiB floor), so the import refuses it unread."""
    from flylib.config import Config
    from flylib.interop import import_points2d
    from flylib.interop.views import view_names

    recording = tmp_path / "recording"
    recording.mkdir()
    (recording / "camera_0.mp4").symlink_to(df3d_sample_dir / "camera_0.mp4")
    target = recording / "rh.analysis.h5"
    shutil.copy(sleap_file, target)
    _replace(
        target,
        "tracks",
        lambda f, n: f.create_dataset(
            n, shape=(1, 2, 3, 10**7), dtype="<f8", chunks=(1, 2, 3, 4096)
        ),
    )
    config = Config.default()
    files = {v: None for v in view_names(config)} | {"rh": "rh.analysis.h5"}
    with pytest.raises(ImportFormatError) as err:
        import_points2d(import_target(config), recording, {"format": "sleap", "files": files})
    text = str(err.value)
    assert text.startswith(str(target)) and "\n" not in text, text
    assert "declares (1, 2, 3, 10000000)" in text and "more than the 64 MiB" in text, text
