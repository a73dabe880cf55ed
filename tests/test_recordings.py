"""Recording discovery: footage matching, batches, ids, output directories, sheets."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from flylib.config import Config
from flylib.config.sources import source_patterns
from flylib.errors import ConfigError, FootageError
from flylib.io import VideoWriter
from flylib.pipeline.planning import plan_recordings
from flylib.recordings import find_recording, resolve_recordings

SOURCES = {
    "sources": [{"name": "left", "filename": "cam_0*"}, {"name": "right", "filename": "cam_1*"}]
}


def plan(data: dict) -> list:
    """The recordings a run of the config ``data`` plans."""
    return plan_recordings(Config.from_dict(data))


def write_video(path: Path, frames: int) -> Path:
    with VideoWriter(path, fps=10) as writer:
        writer.write_frames(np.zeros((frames, 16, 16, 3), np.uint8))
    return path


def write_images(directory: Path, stem: str, frames: int) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / f"{stem}_img_{i}.png" for i in range(frames)]
    for p in paths:
        cv2.imwrite(str(p), np.zeros((8, 8, 3), np.uint8))
    return paths


def make_video_recording(directory: Path, frames=(3, 3)) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    for i, n in enumerate(frames):
        write_video(directory / f"cam_{i}.mp4", n)
    return directory


def test_image_sequences_are_naturally_sorted(tmp_path):
    write_images(tmp_path, "cam_0", 12)
    write_images(tmp_path, "cam_1", 12)
    sources = find_recording(tmp_path, source_patterns(SOURCES))
    names = [p.name for p in sources["left"]]
    assert names[:3] == ["cam_0_img_0.png", "cam_0_img_1.png", "cam_0_img_2.png"]
    assert names[-2:] == ["cam_0_img_10.png", "cam_0_img_11.png"]


def test_one_extension_per_source_prefers_the_video(tmp_path):
    make_video_recording(tmp_path)
    write_images(tmp_path, "cam_0", 3)
    write_images(tmp_path, "cam_1", 3)
    sources = find_recording(tmp_path, source_patterns(SOURCES))
    assert sources == {"left": [tmp_path / "cam_0.mp4"], "right": [tmp_path / "cam_1.mp4"]}


def test_images_are_used_when_not_every_source_has_a_video(tmp_path):
    write_video(tmp_path / "cam_0.mp4", 3)
    write_images(tmp_path, "cam_0", 3)
    write_images(tmp_path, "cam_1", 3)
    sources = find_recording(tmp_path, source_patterns(SOURCES))
    assert all(p.suffix == ".png" for files in sources.values() for p in files)


def test_unequal_frame_counts_are_rejected_with_the_counts(tmp_path, caplog):
    make_video_recording(tmp_path, frames=(3, 5))
    with caplog.at_level(logging.WARNING):
        assert find_recording(tmp_path, source_patterns(SOURCES)) is None
    assert "different frame counts" in caplog.text and "'right': 5" in caplog.text
    with pytest.raises(FootageError, match="frame counts"):
        find_recording(tmp_path, source_patterns(SOURCES), strict=True)
    assert find_recording(tmp_path, source_patterns(SOURCES), check_frames=False) is not None


def test_missing_source_and_unreadable_video_are_named(tmp_path):
    write_video(tmp_path / "cam_0.mp4", 3)
    with pytest.raises(FootageError, match=r"no footage for source\(s\) right"):
        find_recording(tmp_path, source_patterns(SOURCES), strict=True)
    (tmp_path / "cam_1.mp4").write_bytes(b"garbage")
    with pytest.raises(FootageError, match="cam_1.mp4"):
        find_recording(tmp_path, source_patterns(SOURCES), strict=True)


def test_batch_skips_malformed_directories_and_an_empty_batch_is_an_error(tmp_path, caplog):
    good = make_video_recording(tmp_path / "good")
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes.txt").write_text("not a recording")
    with caplog.at_level(logging.WARNING):
        found = resolve_recordings([tmp_path / "*"], recursive=False, config=SOURCES)
    assert [p for p, _ in found] == [good]
    assert "empty" in caplog.text
    with pytest.raises(FootageError, match="none of"):
        resolve_recordings(
            [tmp_path / "empty", tmp_path / "notes.txt"], recursive=False, config=SOURCES
        )


def test_single_literal_path_is_kept_even_without_footage(tmp_path):
    (tmp_path / "rec").mkdir()
    assert resolve_recordings([tmp_path / "rec"], recursive=False, config=SOURCES) == [
        (tmp_path / "rec", {})
    ]


def test_recursive_search_finds_nested_recordings_but_not_outputs(tmp_path):
    a = make_video_recording(tmp_path / "day1" / "fly1")
    b = make_video_recording(tmp_path / "day2" / "fly10")
    c = make_video_recording(tmp_path / "day2" / "fly2")
    make_video_recording(tmp_path / "day2" / "fly2" / "flylib_outputs")
    found = [p for p, _ in resolve_recordings([tmp_path], recursive=True, config=SOURCES)]
    assert found == [a, c, b]  # natural order within a parent
    with pytest.raises(FootageError, match="recursively"):
        resolve_recordings([tmp_path / "day1" / "nothing"], recursive=True, config=SOURCES)


def test_ids_are_unique_and_outdirs_follow_the_template(tmp_path):
    a = make_video_recording(tmp_path / "x" / "session")
    b = make_video_recording(tmp_path / "y" / "session")
    c = make_video_recording(tmp_path / "y" / "other")
    config = {**SOURCES, "recordings": [str(a), str(b), str(c)]}
    recs = plan(config)
    assert [r.id for r in recs] == ["x-session", "y-session", "other"]
    assert [r.outdir for r in recs] == [p / "flylib_outputs" for p in (a, b, c)]
    assert plan(config) == recs  # stable

    config["outdir"] = str(tmp_path / "results" / "{id}")
    assert plan(config)[1].outdir == tmp_path / "results" / "y-session"
    config["outdir"] = str(tmp_path / "results" / "{name}")  # both sessions -> one dir
    with pytest.raises(ConfigError, match="distinct outdirs"):
        plan(config)


def test_entries_and_sheet_carry_outdir_and_import(tmp_path):
    a = make_video_recording(tmp_path / "a")
    b = make_video_recording(tmp_path / "b")
    sheet = tmp_path / "recordings.tsv"
    sheet.write_text(
        "path\toutdir\timport_format\timport_files\n"
        f"a\t{tmp_path / 'out_a'}\tdlc_csv\tleft=l.csv;right=r.csv\n"
        "b\t\t\t\n"
    )
    recs = plan({**SOURCES, "recordings": str(sheet)})
    assert [r.path for r in recs] == [a, b]
    assert recs[0].outdir == tmp_path / "out_a" and recs[1].outdir == b / "flylib_outputs"
    assert recs[0].import_spec == {
        "format": "dlc_csv",
        "files": {"left": "l.csv", "right": "r.csv"},
    }
    assert recs[1].import_spec is None

    recs = plan({**SOURCES, "recordings": [{"path": str(a), "import": {"format": "sleap"}}]})
    assert recs[0].import_spec == {"format": "sleap"}
    with pytest.raises(ConfigError, match="unknown key"):
        plan({**SOURCES, "recordings": [{"path": str(a), "colour": "red"}]})
    with pytest.raises(ConfigError, match="sheet"):
        plan({**SOURCES, "recordings": str(tmp_path / "missing.tsv")})


def test_a_csv_sheet_saved_by_a_spreadsheet_lists_recordings_like_a_tsv_one(tmp_path):
    a = make_video_recording(tmp_path / "data" / "a")
    b = make_video_recording(tmp_path / "data" / "b.csv")  # a folder, not a sheet
    (tmp_path / "sheets").mkdir()
    sheet = tmp_path / "sheets" / "recordings.csv"
    sheet.write_text("\ufeffpath,import_format,import_files\n../data/a,dlc_csv,{stem}DLC_*.csv\n")
    recs = plan({**SOURCES, "recordings": str(sheet)})
    assert [r.path.resolve() for r in recs] == [a.resolve()]
    assert recs[0].import_spec == {"format": "dlc_csv", "files": "{stem}DLC_*.csv"}
    assert [r.path for r in plan({**SOURCES, "recordings": [str(b)]})] == [b]
    sheet.write_text("path;outdir\n../data/a;out\n")  # a spreadsheet set to ';' separators
    with pytest.raises(ConfigError, match=r"needs a 'path' column \(has \['path;outdir'\]\)"):
        plan({**SOURCES, "recordings": str(sheet)})


def test_demo_entry_needs_no_footage_yet(tmp_path):
    config = Config.default().data
    config = {**config, "recordings": [{"path": str(tmp_path / "demo"), "demo": True}]}
    (rec,) = plan(config)
    assert rec.demo and rec.id == "demo" and rec.sources == {}
    assert rec.import_spec["format"] == "dlc_csv"
    assert set(rec.import_spec["files"]) == {"rh", "rm", "rf", "f", "lf", "lm", "lh"}


def test_real_sample_resolves_to_its_videos_or_its_image_sequences(df3d_sample_dir):
    config = Config.default()
    sources = find_recording(df3d_sample_dir, source_patterns(config))
    assert sources["vid_rh"] == [df3d_sample_dir / "camera_0.mp4"]
    images = {
        "sources": [{"name": f"cam{i}", "filename": f"camera_{i}_img_*.jpg"} for i in range(7)]
    }
    sources = find_recording(df3d_sample_dir, source_patterns(images))
    assert len(sources["cam3"]) == 15
    assert (
        sources["cam3"][2].name == "camera_3_img_2.jpg"
        and sources["cam3"][-1].name == "camera_3_img_14.jpg"
    )


def test_plan_skips_a_malformed_batch_member_with_a_warning(tmp_path, caplog):
    good = make_video_recording(tmp_path / "good")
    bad = make_video_recording(tmp_path / "bad", frames=(3, 4))
    with caplog.at_level(logging.WARNING):
        recs = plan({**SOURCES, "recordings": [str(good), str(bad)]})
    assert [r.path for r in recs] == [good]
    assert f"skipping {bad}" in caplog.text and "frame counts" in caplog.text
    (tmp_path / "empty").mkdir()
    with pytest.raises(FootageError, match="none of"):
        plan({**SOURCES, "recordings": [str(bad), str(tmp_path / "empty")]})


@pytest.mark.parametrize("batch", [False, True])
def test_a_mistyped_or_file_path_is_one_clear_error_naming_the_entry(tmp_path, batch):
    good = make_video_recording(tmp_path / "fly_07")
    others = [str(good)] if batch else []
    with pytest.raises(ConfigError) as info:
        plan({**SOURCES, "recordings": [*others, str(tmp_path / "fyl_07")]})
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"recordings[{len(others)}]: {tmp_path / 'fyl_07'} does not exist")
    assert f"did you mean {good}?" in message
    with pytest.raises(ConfigError, match="does not exist; fix the path"):
        plan({**SOURCES, "recordings": [*others, str(tmp_path / "zzzzzzzz" / "q")]})
    (tmp_path / "notes.txt").write_text("not a recording")
    with pytest.raises(ConfigError, match=r"notes.txt is a file, not a directory"):
        plan({**SOURCES, "recordings": [*others, {"path": str(tmp_path / "notes.txt")}]})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fly_07", "notes.txt"]  # nothing created


# -- outdir templates: only the documented placeholders (issue 37, case 6) ---------------


@pytest.mark.parametrize(
    ("template", "field"),
    [
        ("out/{name!r}", "{name!r}"),
        ("out/{recording.__class__}", "{recording.__class__}"),
        ("out/{id[0]}", "{id[0]}"),
        ("out/{id:>9}", "{id:>9}"),
        ("out/{foo}", "{foo}"),
        ("out/{}", "{}"),
    ],
)
def test_an_outdir_template_takes_only_plain_documented_placeholders(
    tmp_path, capsys, monkeypatch, template, field
):
    from flylib.cli import main

    monkeypatch.chdir(tmp_path)
    default = Path(__file__).resolve().parents[1] / "config" / "config.yaml"
    (tmp_path / "my.yaml").write_text(f"outdir: '{template}'\n")
    assert main(["check-config", str(default), "my.yaml"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (
        f"flylib check-config: invalid config: my.yaml: outdir: {field} in {template!r} is not "
        "a placeholder; use only {recording}, {id}, {name}, written plain (e.g. results/{id})"
    )
    (tmp_path / "my.yaml").write_text(
        f"recordings:\n  - {{path: demo, demo: true, outdir: '{template}'}}\n"
    )
    assert main(["check-config", str(default), "my.yaml"]) == 1
    assert "my.yaml: recordings[0].outdir: " in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_outdir_template_fills_its_placeholders_and_literal_braces(
    tmp_path, capsys, monkeypatch
):
    from flylib.cli import main
    from flylib.paths import fill_template

    monkeypatch.chdir(tmp_path)
    default = Path(__file__).resolve().parents[1] / "config" / "config.yaml"
    (tmp_path / "my.yaml").write_text("outdir: 'out/{id}-{name}'\n")
    assert main(["check-config", str(default), "my.yaml"]) == 0
    assert "demo -> out/demo-demo" in capsys.readouterr().out
    assert fill_template("out/{{x}}/{id}", {"id": "a"}, "outdir") == "out/{x}/a"
    # a literal brace fills, but Snakemake cannot take a folder path holding braces
    (tmp_path / "my.yaml").write_text("outdir: 'out/{{x}}/{id}-{name}'\n")
    assert main(["check-config", str(default), "my.yaml"]) == 1
    assert "the output folder's path holds {x}" in capsys.readouterr().err
    (tmp_path / "my.yaml").write_text("outdir: 'out/{id'\n")
    assert main(["check-config", str(default), "my.yaml"]) == 1
    assert (
        capsys.readouterr()
        .err.strip()
        .startswith(
            "flylib check-config: invalid config: my.yaml: outdir: 'out/{id' is not a path template"
        )
    )


@pytest.fixture
def frame_counts(tmp_path, monkeypatch):
    """A frame-count cache of this test's own, as the process's, and a list of the
    videos whose headers were read."""
    from flylib.recordings import frame_counts as counts

    cache = counts.FrameCountCache(lambda: tmp_path / "cache")
    monkeypatch.setattr(counts, "FRAME_COUNTS", cache)
    opened = []
    real_read = counts.header_frame_count

    def counted(path):
        opened.append(path)
        return real_read(path)

    monkeypatch.setattr(counts, "header_frame_count", counted)
    return cache, opened


def test_planning_a_batch_again_opens_none_of_its_videos(tmp_path, frame_counts, caplog):
    """The second plan of a batch reads every frame count from the cache, and still
    skips the recording whose cameras disagree."""
    from flylib.recordings import frame_counts as counts

    cache, opened = frame_counts
    good = make_video_recording(tmp_path / "good")
    uneven = make_video_recording(tmp_path / "uneven", frames=(3, 4))
    data = {**SOURCES, "recordings": [str(good), str(uneven)]}
    for run in range(2):
        caplog.clear()
        assert [r.path for r in plan(data)] == [good], run
        assert "different frame counts {'left': 3, 'right': 4}" in caplog.text, run
        assert len(opened) == 4, run  # the second run opened none
        cache.flush()  # as the process's exit does
        cache = counts.FrameCountCache(lambda: tmp_path / "cache")  # the next run's
        counts.FRAME_COUNTS = cache


def test_a_rewritten_video_is_counted_again(tmp_path, frame_counts):
    from flylib.recordings.frame_counts import video_frame_count

    _, opened = frame_counts
    video = write_video(tmp_path / "cam_0.mp4", 3)
    assert video_frame_count(video) == 3 and video_frame_count(video) == 3
    assert len(opened) == 1
    write_video(video, 5)  # the same path, another file
    assert video_frame_count(video) == 5 and len(opened) == 2


def test_a_cache_folder_that_cannot_be_made_is_passed_by(tmp_path, monkeypatch):
    from flylib.recordings import frame_counts as counts

    (tmp_path / "blocker").write_text("a file where the cache folder would be")
    cache = counts.FrameCountCache(lambda: tmp_path / "blocker" / "cache")
    monkeypatch.setattr(counts, "FRAME_COUNTS", cache)
    video = write_video(tmp_path / "cam_0.mp4", 4)
    assert counts.video_frame_count(video) == 4 and counts.video_frame_count(video) == 4


@pytest.mark.parametrize(
    "codec, name, options",
    [
        ("libx264", "cam.mp4", {}),  # B-frames: an edit list
        ("libx264", "cam.mov", {}),  # QuickTime: a second hdlr, the data handler's
        ("libx264", "cam.mp4", {"movflags": "faststart"}),  # moov before mdat
        ("mpeg4", "cam.mp4", {}),
        ("mjpeg", "cam.mov", {}),
        ("libx264", "cam.mp4", {"movflags": "frag_keyframe+empty_moov"}),  # fragmented: av
        ("libx264", "cam.mkv", {}),  # not MP4: av
    ],
)
def test_a_videos_frame_count_is_the_one_av_reports(tmp_path, codec, name, options):
    """The frame count read from an MP4's sample table (no decoder opened) is av's, and
    any file that reader is not sure of is counted by av."""
    import av

    from flylib.recordings.frame_counts import header_frame_count, mp4_frame_count

    path = tmp_path / name
    with av.open(str(path), "w", options=options) as container:
        stream = container.add_stream(codec, rate=30)
        stream.width, stream.height = 64, 48
        stream.pix_fmt = "yuvj420p" if codec == "mjpeg" else "yuv420p"
        rng = np.random.default_rng(0)
        for _ in range(37):
            image = rng.integers(0, 255, (48, 64, 3), np.uint8)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())
    with av.open(str(path)) as container:
        reported = container.streams.video[0].frames or None
    assert header_frame_count(path) == reported
    read_by_av = name.endswith(".mkv") or "frag" in options.get("movflags", "")
    assert mp4_frame_count(path) == (None if read_by_av else 37)
