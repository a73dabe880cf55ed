"""Shared set-up of the GUI and corrections tests: a small demo recording run through the
stage functions (2D imported from its DeepLabCut CSVs, triangulated with the config rig,
assembled), and a corrections sidecar written by hand from the seed GUI's documented
layout (``../shared/spec/corrections-h5.md``), not by flylib's writer."""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np

from flylib.pipeline.inputs import stage_inputs


def make_demo_outputs(
    directory: Path, frames: int = 12, displaced=(), recording_dir=None, **demo
) -> Path:
    """Demo recording in ``directory``; returns its output directory (with results.h5).

    ``recording_dir``: the recording path the stages are given (default ``directory``;
    a relative one is relative to the current directory, as in a workflow run there).
    ``displaced``: ``(camera, point name, frames, (dx, dy))`` detector mistakes written
    into the demo's DeepLabCut CSVs before the import (a suspect spanning those frames).
    """
    from flylib.config import Config
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.demo import demo_import_spec, make_demo
    from flylib.pipeline.pose2d import run_pose2d
    from flylib.pipeline.triangulation import run_triangulation

    data = Config.default().data
    data["pipeline"]["do_bundle_adjustment"] = False  # what is run below: the config rig
    config = Config.from_dict(data)
    make_demo(config, directory, frames=frames, **demo)
    for camera, point, at, dxy in displaced:
        displace_dlc(directory / f"{camera}DLC_flylibdemo.csv", point, at, dxy)
    out = directory / "flylib_outputs"
    run_pose2d(
        stage_inputs(config, "pose2d"),
        directory,
        out / "stages" / "pose2d.h5",
        import_spec=demo_import_spec(config),
    )
    run_triangulation(
        stage_inputs(config, "triangulation"),
        out / "stages" / "pose2d.h5",
        out / "stages" / "triangulation.h5",
        recording_dir=recording_dir or directory,
    )
    run_assemble(
        stage_inputs(config, "assemble"),
        {
            "pose2d": out / "stages" / "pose2d.h5",
            "triangulation": out / "stages" / "triangulation.h5",
        },
        out,
        recording_dir=recording_dir or directory,
    )
    config.save_snapshot(out)
    return out


def make_corrected_outputs(directory: Path, frames: int = 12):
    """The demo with a hand-made sidecar applied (a 2D edit at frame 4, a point marked invisible
    at frame 7), re-triangulated and re-assembled as the workflow does: ``(outdir, (view, point,
    edited xy), (view, point made invisible))``."""
    from flylib.config import Config
    from flylib.corrections import Corrections
    from flylib.pipeline.assemble import run_assemble
    from flylib.pipeline.stage_helpers import run_inputs
    from flylib.pipeline.triangulation import run_triangulation
    from flylib.results import PoseResult

    out = make_demo_outputs(directory, frames=frames)
    config = Config.from_file(out / "config.yaml")
    before = PoseResult.load(out / "results.h5")
    v, t, p = before.pts2d.shape[:3]
    seen = np.isfinite(before.pts2d).all(-1)
    view_a, point_a = map(int, np.argwhere(seen[:, 4])[0])
    edit_xy = before.pts2d[view_a, 4, point_a] + [6.0, -4.0]
    view_b, point_b = map(int, np.argwhere(seen[:, 7])[5])
    corrections = Corrections.empty(v, t, p)
    corrections.set_point(view_a, 4, point_a, edit_xy, fixed=True)
    corrections.set_invisible(view_b, 7, point_b)
    sidecar = corrections.save(out / "corrections.h5")
    stages = out / "stages"
    run_triangulation(
        run_inputs(config, "triangulation"),
        stages / "pose2d.h5",
        stages / "triangulation.h5",
        recording_dir=out.parent,
        corrections_path=sidecar,
    )
    run_assemble(
        stage_inputs(config, "assemble"),
        {"pose2d": stages / "pose2d.h5", "triangulation": stages / "triangulation.h5"},
        out,
        recording_dir=out.parent,
    )
    return out, (view_a, point_a, edit_xy), (view_b, point_b)


def displace_dlc(path: Path, point: str, frames, dxy) -> None:
    """Move ``point`` by ``dxy`` pixels at ``frames`` in a DeepLabCut CSV (in place)."""
    import csv

    rows = list(csv.reader(path.read_text().splitlines()))
    column = rows[1].index(point)
    for row in rows[3:]:
        if int(row[0]) in frames:
            row[column] = str(float(row[column]) + dxy[0])
            row[column + 1] = str(float(row[column + 1]) + dxy[1])
    with path.open("w", newline="") as f:
        csv.writer(f).writerows(rows)


def write_seed_sidecar(
    path: Path,
    shape: tuple[int, int, int],
    *,
    version: int = 3,
    edits2d=(),
    invisible=(),
    edits3d=(),
    fixed=(),
) -> Path:
    """A corrections.h5 in the seed GUI's layout, written with plain h5py.

    ``edits2d``: ``(view, frame, point, x, y)``; ``invisible``: ``(view, frame, point)``;
    ``edits3d``: ``(frame, point, x, y, z)``; ``fixed``: ``(view, frame, point)`` among the
    2D edits. Version 2 files have no ``invisible`` mask, version 1 no ``fixed`` either.
    """
    v, t, p = shape
    points = np.full((v, t, p, 2), np.nan)
    edited = np.zeros((v, t, p), bool)
    fixed_mask = np.zeros((v, t, p), bool)
    invisible_mask = np.zeros((v, t, p), bool)
    for vi, ti, pi, x, y in edits2d:
        points[vi, ti, pi] = (x, y)
        edited[vi, ti, pi] = True
    for vi, ti, pi in fixed:
        fixed_mask[vi, ti, pi] = True
    for vi, ti, pi in invisible:
        invisible_mask[vi, ti, pi] = True
    points3d = np.full((t, p, 3), np.nan)
    edited3d = np.zeros((t, p), bool)
    for ti, pi, x, y, z in edits3d:
        points3d[ti, pi] = (x, y, z)
        edited3d[ti, pi] = True
    with h5py.File(path, "w") as f:
        f.attrs["meta"] = json.dumps(
            {
                "deeperfly_corrections_format_version": version,
                "source": "results.h5",
                "created_utc": "2025-01-01T00:00:00+00:00",
            }
        )
        g = f.create_group("pose2d_corrections")
        g["points"] = points
        g["edited"] = edited
        if version >= 2:
            g["fixed"] = fixed_mask
        if version >= 3:
            g["invisible"] = invisible_mask
        g3 = f.create_group("pose3d_corrections")
        g3["points3d"] = points3d
        g3["edited"] = edited3d
    return path


#: A name that runs script wherever a page builds HTML from data (a stored XSS).
HOSTILE_NAME = '<img src=x onerror="window.flylibPwned=1">'


def rename_hostile(outdir: Path) -> tuple[str, str]:
    """Rewrite ``outdir/results.h5`` with its first camera and first point renamed to
    script-carrying HTML (as a foreign or tampered results.h5 could hold); returns the
    two new names."""
    from dataclasses import replace

    from flylib.camera.rig import CameraGroup
    from flylib.results import PoseResult

    result = PoseResult.load(outdir / "results.h5")
    camera, point = HOSTILE_NAME, HOSTILE_NAME.replace("=1", "=2")
    old_camera = result.cameras.names[0]
    old_point = result.skeleton.point_names[0]
    cameras = CameraGroup(
        {
            (camera if name == old_camera else name): replace(
                cam, name=camera if name == old_camera else name
            )
            for name, cam in zip(result.cameras.names, result.cameras, strict=True)
        }
    )
    rename = {old_point: point}
    skeleton = replace(
        result.skeleton,
        point_names=tuple(rename.get(p, p) for p in result.skeleton.point_names),
        limbs={k: tuple(rename.get(p, p) for p in v) for k, v in result.skeleton.limbs.items()},
    )
    sizes = result.image_sizes or {}
    image_sizes = {
        (camera if name == old_camera else name): size for name, size in sizes.items()
    } or None
    replace(result, cameras=cameras, skeleton=skeleton, image_sizes=image_sizes).save(
        outdir / "results.h5"
    )
    return camera, point


@contextmanager
def serving(session):
    """``flylib gui``'s app for ``session`` on a free localhost port in a thread; yields
    the page's URL and stops the server (not the session) afterwards."""
    import socket
    import threading
    import time

    import uvicorn

    from flylib.gui import create_app

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    app = create_app(session)
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    app.state.stop = lambda: setattr(srv, "should_exit", True)
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.time() + 30
    while not srv.started and time.time() < deadline:
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}/"
    finally:
        srv.should_exit = True
        thread.join(10)
