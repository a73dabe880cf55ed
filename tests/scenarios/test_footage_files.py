"""Footage that is not what its name says (issue 37, cases 17 and 18): an image sequence
whose numbering skips a frame, and a video name that is a FIFO or a link to /dev/zero.
Each stops the run before its DAG with one line naming the file, never a silent shift of
frames or a misleading "view has no footage"."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from flylib import io
from flylib.config.sources import source_patterns
from flylib.errors import FootageError
from flylib.recordings import find_recording

from workflow_run import snakemake_command

REPO = Path(__file__).resolve().parents[2]
N_FRAMES = 15


def _images(directory: Path, camera: int, numbers, size=(24, 32)) -> None:
    rng = np.random.default_rng(camera)
    for i in numbers:
        image = rng.integers(0, 255, (*size, 3), dtype=np.uint8)
        cv2.imwrite(str(directory / f"camera_{camera}_img_{i}.jpg"), image)


@pytest.fixture(scope="module")
def demo_recording(tmp_path_factory) -> tuple[Path, dict]:
    """A synthetic recording with one DeepLabCut CSV per view (its videos too), and the
    import spec that reads the CSVs."""
    from flylib.config import Config
    from flylib.pipeline.demo import demo_import_spec, make_demo

    root = tmp_path_factory.mktemp("footage") / "rec"
    config = Config.from_file(REPO / "config" / "config.yaml")
    make_demo(config, root, frames=N_FRAMES, seed=0)
    return root, demo_import_spec(config)


def _workdir(tmp_path: Path, recording: Path, spec: dict, sources=None) -> Path:
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["recordings"] = [str(recording)]
    config["outdir"] = str(tmp_path / "out")
    config["pose2d"]["import"] = spec
    if sources is not None:
        config["sources"] = sources
    workdir = tmp_path / "work"
    workdir.mkdir()
    (workdir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return workdir


def _dry_run(workdir: Path) -> tuple[int, str]:
    proc = subprocess.run(
        snakemake_command(workdir, "--dry-run"),
        capture_output=True,
        text=True,
        timeout=600,
        cwd=workdir,
        check=False,
    )
    return proc.returncode, proc.stdout + proc.stderr


def _image_recording(source: Path, tmp_path: Path, gap_camera: int | None) -> Path:
    """The demo's CSVs with an image sequence per camera instead of videos, camera
    ``gap_camera`` lacking image 7 (numbered 0..6, 8..15: as many images as frames)."""
    recording = tmp_path / "rec"
    recording.mkdir()
    for csv in source.glob("*.csv"):
        shutil.copy(csv, recording / csv.name)
    for camera in range(7):
        numbers = range(N_FRAMES)
        if camera == gap_camera:
            numbers = [*range(7), *range(8, N_FRAMES + 1)]
        _images(recording, camera, numbers)
    return recording


IMAGE_SOURCES = [
    {"name": f"vid_{v}", "filename": f"camera_{i}_img_*.jpg"}
    for i, v in enumerate(["rh", "rm", "rf", "f", "lf", "lm", "lh"])
]


@pytest.mark.slow
def test_a_gap_in_an_image_sequence_stops_the_run_naming_the_missing_image(
    demo_recording, tmp_path
):
    source, spec = demo_recording
    recording = _image_recording(source, tmp_path, gap_camera=3)
    code, out = _dry_run(_workdir(tmp_path, recording, spec, IMAGE_SOURCES))
    assert code == 1, out[-3000:]
    assert (
        f"recordings[0]: {recording}: the image sequence camera_3_img_0.jpg .. "
        f"camera_3_img_15.jpg lacks 1 frame(s): camera_3_img_7.jpg (the number in each "
        "image's name is its frame); restore the missing images"
    ) in out
    assert "Building DAG" not in out


@pytest.mark.slow
def test_image_sequences_without_a_gap_plan_the_run(demo_recording, tmp_path):
    source, spec = demo_recording
    recording = _image_recording(source, tmp_path, gap_camera=None)
    code, out = _dry_run(_workdir(tmp_path, recording, spec, IMAGE_SOURCES))
    assert code == 0, out[-3000:]
    assert "rule pose2d" in out


@pytest.mark.slow
@pytest.mark.parametrize(
    ("make", "what"),
    [
        (lambda p: os.mkfifo(p), "is a named pipe (FIFO), not a video or image file"),
        (
            lambda p: os.symlink("/dev/zero", p),
            "is a link to /dev/zero, a character device, not a video or image file",
        ),
    ],
    ids=["fifo", "dev-zero"],
)
def test_a_video_that_is_no_file_is_named_before_the_dag(demo_recording, tmp_path, make, what):
    source, spec = demo_recording
    recording = tmp_path / "rec"
    shutil.copytree(source, recording)
    video = recording / "camera_5.mp4"
    video.unlink()
    make(video)
    code, out = _dry_run(_workdir(tmp_path, recording, spec))
    assert code == 1, out[-3000:]
    assert f"recordings[0]: {video}: {what}; replace it with the footage file" in out
    assert "has no footage" not in out and "Building DAG" not in out


def test_a_reader_refuses_a_sequence_with_a_gap_or_a_frame_twice(tmp_path):
    _images(tmp_path, 0, [*range(7), *range(8, 15)])
    with pytest.raises(FootageError, match=r"lacks 1 frame\(s\): camera_0_img_7\.jpg "):
        io.open_reader(tmp_path / "camera_0_img_*.jpg")
    (tmp_path / "camera_0_img_7.jpg").write_bytes((tmp_path / "camera_0_img_6.jpg").read_bytes())
    assert io.open_reader(tmp_path / "camera_0_img_*.jpg").count() == 15
    shutil.copy(tmp_path / "camera_0_img_3.jpg", tmp_path / "camera_0_img_03.jpg")
    with pytest.raises(
        FootageError,
        match=r"images camera_0_img_03\.jpg and camera_0_img_3\.jpg both number frame 3",
    ):
        io.open_reader(tmp_path / "camera_0_img_*.jpg")


def test_zero_padded_names_name_the_missing_files_padded(tmp_path):
    for i in [0, 1, 2, 5, 6]:
        shutil.copy(_one_image(tmp_path), tmp_path / f"frame_{i:04d}.png")
    with pytest.raises(
        FootageError, match=r"lacks 2 frame\(s\): frame_0003\.png, frame_0004\.png "
    ):
        io.open_reader(tmp_path / "frame_*.png")


def _one_image(tmp_path: Path) -> Path:
    path = tmp_path / "one.bmp"
    cv2.imwrite(str(path), np.zeros((4, 4, 3), np.uint8))
    return path


def test_find_recording_rejects_a_gap_and_a_fifo(tmp_path):
    sources = {"sources": [{"name": "a", "filename": "camera_0_img_*.jpg"}]}
    _images(tmp_path, 0, [0, 1, 3])
    with pytest.raises(FootageError, match="lacks 1 frame"):
        find_recording(tmp_path, source_patterns(sources), strict=True)
    assert find_recording(tmp_path, source_patterns(sources)) is None  # a batch skips it
    os.mkfifo(tmp_path / "cam.mp4")
    with pytest.raises(FootageError, match=r"cam\.mp4: is a named pipe"):
        find_recording(tmp_path, {"a": "cam.mp4"}, strict=True)
