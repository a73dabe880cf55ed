"""Camera rigs from calibration files: Anipose TOML, DeepFly3D pickle, calibrations.csv.

Anipose TOML: one ``[cam_N]`` table per camera with ``name``, ``size = [width, height]``, ``matrix``
(3x3 K), ``distortions`` (OpenCV ``k1 k2 p1 p2 k3``), ``rotation`` (Rodrigues, world to camera) and
``translation``; optional ``[metadata]``. OpenCV's camera model, as flylib's.

Config (top-level ``calibration`` table), the rig from a file instead of the orbit parameters::

    calibration:
      file: calibration.toml     # or a DeepFly3D calib pickle
      format: anipose            # anipose | deepfly3d (default: from the suffix)
      names: {rh: cam_a, ...}    # optional: view -> camera name (anipose) or index (deepfly3d)
      mirror: false              # true: mirror the file's world (flylib.handedness.mirror_cameras)
    # or, resolving a recording's file by its session name:
    calibration:
      index: calibrations.csv    # rows "<...>/<session>/<image>,<toml path>"
      session: null              # default: the recording directory's name

Anipose cameras match views by ``name``, DeepFly3D cameras by index in config order. Relative paths
resolve against the recording directory, else the config file's directory, else the working
directory; paths inside ``calibrations.csv`` are relative to the CSV."""

from __future__ import annotations

import logging
import os
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from ..config.loading import MAX_NESTING, toml_dotted_line
from ..errors import FootageError, ImportFormatError
from ..paths import atomic_path
from .calib_checks import camera_value, image_size

log = logging.getLogger(__name__)

CALIBRATION_FORMATS = ("anipose", "deepfly3d")


def read_anipose_toml(path: Path) -> dict[str, dict]:
    """Read an Anipose calibration TOML: ``camera name -> dict`` in ``cam_N`` order, with ``size``
    ``(width, height)`` (or ``None``) and float64 ``kmat`` (3, 3), ``dist`` (K,), ``rvec``, ``tvec``;
    a K with skew or a last row other than ``[0, 0, 1]`` is an :class:`ImportFormatError`."""
    path = Path(path)
    if not path.is_file():
        raise ImportFormatError(f"{path}: no such Anipose calibration file; check calibration.file")
    try:
        text = path.read_text(encoding="utf-8")
        if toml_dotted_line(text) is not None:
            raise RecursionError
        data = tomllib.loads(text)
    except RecursionError:
        raise ImportFormatError(
            f"{path}: nested more than {MAX_NESTING} levels deep; an Anipose calibration "
            "holds one table per camera, fix the file"
        ) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        detail = " ".join(str(exc).split())
        raise ImportFormatError(f"{path}: not valid TOML ({detail}); fix the syntax") from None
    except OSError as exc:
        raise ImportFormatError(
            f"{path}: cannot read the calibration ({exc.strerror or exc})"
        ) from None
    tables = {k: v for k, v in data.items() if k.startswith("cam_") and isinstance(v, dict)}

    def order(key: str):
        suffix = key[4:]
        return (0, int(suffix), "") if suffix.isdigit() else (1, 0, suffix)

    out: dict[str, dict] = {}
    for key in sorted(tables, key=order):
        table = tables[key]
        name = table.get("name", key)
        name = str(name) if isinstance(name, int) and not isinstance(name, bool) else name
        if not isinstance(name, str) or not name:
            raise ImportFormatError(
                f"{path} [{key}]: 'name' is {name!r}; it must be the camera's name (text)"
            )
        where = f"{path} [{key}] (name {name!r})"
        missing = [
            k for k in ("matrix", "distortions", "rotation", "translation") if k not in table
        ]
        if missing:
            raise ImportFormatError(f"{where}: lacks {missing}; see the Anipose calibration format")
        kmat = camera_value(table["matrix"], "matrix", where, "matrix")
        rvec = camera_value(table["rotation"], "vec3", where, "rotation")
        tvec = camera_value(table["translation"], "vec3", where, "translation")
        dist = camera_value(table["distortions"], "dist", where, "distortions")
        if name in out:
            raise ImportFormatError(
                f"{where}: camera name {name!r} used twice; names must be unique"
            )
        size = table.get("size")
        out[name] = {
            "size": None if size is None else image_size(size, where),
            "kmat": kmat,
            "dist": dist,
            "rvec": rvec,
            "tvec": tvec,
        }
    if not out:
        raise ImportFormatError(f"{path}: no [cam_N] tables; not an Anipose calibration")
    return out


def write_anipose_toml(
    cameras, path: Path, image_sizes: dict | None = None, metadata: dict | None = None
) -> Path:
    """Write a :class:`flylib.camera.rig.CameraGroup` as an Anipose calibration TOML (atomically).

    ``image_sizes``: ``view -> (height, width)``; a camera without one gets ``size = [2 cx, 2 cy]``,
    the best guess Anipose can use. ``metadata``: extra ``[metadata]`` entries."""
    import tomli_w

    image_sizes = image_sizes or {}
    names = list(cameras.names)
    rvecs, tvecs, intrs = (
        np.asarray(a, dtype=np.float64) for a in (cameras.rvecs, cameras.tvecs, cameras.intrs)
    )
    dists = np.asarray(cameras.dists, dtype=np.float64).reshape(len(names), -1)
    doc: dict = {}
    for i, name in enumerate(names):
        fx, fy, cx, cy = (float(v) for v in intrs[i])
        if name in image_sizes:
            h, w = (int(v) for v in image_sizes[name])
        else:
            w, h = int(round(2 * cx)), int(round(2 * cy))
        dist = [float(v) for v in dists[i]]
        dist += [0.0] * (5 - len(dist))  # Anipose reads exactly k1 k2 p1 p2 k3
        doc[f"cam_{i}"] = {
            "name": str(name),
            "size": [w, h],
            "matrix": [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
            "distortions": dist,
            "rotation": [float(v) for v in rvecs[i]],
            "translation": [float(v) for v in tvecs[i]],
        }
    doc["metadata"] = {"written_by": "flylib", **(metadata or {})}
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(tomli_w.dumps(doc).encode())
    return path


def _resolve(path_text: str, recording_dir: Path | None, config_dir: Path | None) -> Path:
    path = Path(os.path.expanduser(str(path_text)))
    if path.is_absolute():
        return path
    for base in (recording_dir, config_dir):
        if base is not None and (Path(base) / path).exists():
            return Path(base) / path
    return path


def _session_parts(text: str) -> tuple[str, ...]:
    """Path components of a calibrations.csv first-column entry (either separator)."""
    return PureWindowsPath(text).parts if "\\" in text else PurePosixPath(text).parts


def calibration_from_index(index_csv: Path, session: str) -> Path:
    """The calibration file ``calibrations.csv`` gives ``session``: rows whose first column is the
    session or has it as a directory (``labeled-data/<session>/img.png``); there must be one file."""
    import pandas as pd

    index_csv = Path(index_csv)
    if not index_csv.is_file():
        raise ImportFormatError(f"{index_csv}: no such calibrations index; check calibration.index")
    try:
        table = pd.read_csv(index_csv, index_col=0, dtype=str)
    except (UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError, OSError) as exc:
        detail = " ".join(str(exc).split())[:300]
        raise ImportFormatError(
            f"{index_csv}: not a readable calibrations index CSV ({detail})"
        ) from None
    if "file" not in table.columns:
        raise ImportFormatError(
            f"{index_csv}: needs a 'file' column (header ',file'); see the calibrations.csv format"
        )
    found = []
    for image, file in zip(table.index.astype(str), table["file"]):
        parts = _session_parts(image)
        if image == session or session in parts[:-1]:
            found.append(file)
    unique = list(dict.fromkeys(found))
    if not unique:
        raise ImportFormatError(
            f"{index_csv}: no row for session {session!r}; add '<...>/{session}/<image>,<calibration.toml>' "
            "or set calibration.session"
        )
    if len(unique) > 1:
        raise ImportFormatError(
            f"{index_csv}: session {session!r} maps to several files {unique}; keep one per session"
        )
    return index_csv.parent / unique[0]


def calibration_file(spec: Mapping, recording_dir: Path | None, config_dir: Path | None) -> Path:
    """The calibration file a ``calibration`` table names (through its index if any), relative paths
    resolved as :func:`load_calibration` resolves them."""
    if "index" in spec:
        return calibration_from_index(
            _resolve(spec["index"], recording_dir, config_dir), _session(spec, recording_dir)
        )
    return _resolve(spec["file"], recording_dir, config_dir)


def _session(spec: Mapping, recording_dir: Path | None) -> str:
    session = spec.get("session") or (Path(recording_dir).name if recording_dir else None)
    if not session:
        raise ImportFormatError(
            "calibration.index needs a recording directory or calibration.session"
        )
    return str(session)


def calibration_inputs(
    calibration: Mapping | None,
    recording_dir: Path | None = None,
    *,
    config_dir: Path | None = None,
) -> list[Path]:
    """The existing files a ``calibration`` table reads for one recording (index CSV, calibration
    file): workflow inputs, so editing them re-runs the rig's stages. Missing ones are left out
    (the stage then fails naming the fix)."""
    spec = calibration
    if not isinstance(spec, Mapping) or not ({"file", "index"} & set(spec)):
        return []
    files = []
    if "index" in spec:
        files.append(_resolve(spec["index"], recording_dir, config_dir))
    try:
        files.append(calibration_file(spec, recording_dir, config_dir))
    except ImportFormatError:
        pass
    return [f for f in dict.fromkeys(files) if f.is_file()]


def load_calibration(
    calibration: Mapping | None,
    views: Sequence[str] = (),
    recording_dir: Path | None = None,
    image_sizes: Mapping[str, tuple[int, int]] | None = None,
    *,
    config_dir: Path | None = None,
):
    """The :class:`flylib.camera.rig.CameraGroup` (one camera per view, ``views`` order; none: the
    file's) from a ``calibration`` table (module docstring).

    ``mirror: true`` mirrors the file's world (same pixels, 3D mirrored). ``recording_dir`` names
    the session for ``calibration.index``. ``image_sizes`` (footage ``(height, width)``) must match
    an Anipose file's sizes, else :class:`FootageError`: a lens calibrated at another resolution."""
    from ..camera.rig import CameraGroup

    spec = calibration
    if not isinstance(spec, Mapping) or not ({"file", "index"} & set(spec)):
        raise ImportFormatError(
            f"config 'calibration' is {spec!r}; give {{file: path, format: anipose|deepfly3d}} "
            "or {index: calibrations.csv}"
        )
    path = calibration_file(spec, recording_dir, config_dir)
    fmt = spec.get("format") or (
        "deepfly3d" if path.suffix.lower() in (".pkl", ".pickle") else "anipose"
    )
    if fmt not in CALIBRATION_FORMATS:
        raise ImportFormatError(
            f"calibration.format is {fmt!r}; use one of {list(CALIBRATION_FORMATS)}"
        )
    views = list(views)
    names = spec.get("names") or {}
    if fmt == "anipose":
        cams = read_anipose_toml(path)
        views = views or list(cams)  # no views configured: the file's cameras, in order
        chosen = [cams.get(str(names.get(v, v))) for v in views]
        _check_calibrated_sizes(path, views, chosen, image_sizes or {}, recording_dir)
    else:
        from .df3d import read_df3d_calibration

        cams_by_index = read_df3d_calibration(path)
        views = views or [str(i) for i in cams_by_index]
        chosen = [cams_by_index.get(int(names.get(v, i))) for i, v in enumerate(views)]
        cams = {str(k): c for k, c in cams_by_index.items()}
    absent = [v for v, c in zip(views, chosen) if c is None]
    if absent:
        raise ImportFormatError(
            f"{path}: no camera for views {absent} (file has {list(cams)}); "
            "set calibration.names {view: camera name or index}"
        )
    kmats = np.stack([c["kmat"] for c in chosen])
    intrs = np.stack([kmats[:, 0, 0], kmats[:, 1, 1], kmats[:, 0, 2], kmats[:, 1, 2]], axis=-1)
    width = max(c["dist"].size for c in chosen)
    dists = np.zeros((len(chosen), width))
    for i, c in enumerate(chosen):
        dists[i, : c["dist"].size] = c["dist"]
    log.info("camera rig for %d views from %s (%s)", len(views), path, fmt)
    rig = CameraGroup.from_arrays(
        list(views),
        np.stack([c["rvec"] for c in chosen]),
        np.stack([c["tvec"] for c in chosen]),
        intrs,
        dists,
    )
    if spec.get("mirror"):  # a calibration whose world is the fly's mirror image
        from ..handedness import mirror_cameras

        log.info("calibration.mirror: %s's world mirrored (z negated)", path)
        rig = mirror_cameras(rig)
    return rig


def _check_calibrated_sizes(path, views, chosen, image_sizes, recording_dir) -> None:
    """Each view's footage (height, width) against its camera's ``size`` ([width, height])."""
    for view, cam in zip(views, chosen):
        footage = image_sizes.get(view)
        if cam is None or cam["size"] is None or footage is None:
            continue
        calibrated = (int(cam["size"][0]), int(cam["size"][1]))
        actual = (int(footage[1]), int(footage[0]))
        if actual != calibrated:
            where = f"{recording_dir}: camera {view}" if recording_dir else f"camera {view}"
            raise FootageError(
                f"{where}: footage is {actual[0]}x{actual[1]} px but {path} calibrated it at "
                f"{calibrated[0]}x{calibrated[1]} px (width x height); use that camera's "
                "original footage or a calibration made at this resolution"
            )


def calibration_image_sizes(path: Path) -> dict[str, tuple[int, int]]:
    """``camera name -> (height, width)`` recorded in an Anipose TOML (cameras with a size)."""
    return {
        name: (cam["size"][1], cam["size"][0])
        for name, cam in read_anipose_toml(path).items()
        if cam["size"] is not None
    }
