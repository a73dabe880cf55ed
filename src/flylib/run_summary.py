"""The end-of-run table, printed by the workflow's ``onsuccess`` / ``onerror`` handlers so the
answer is the last thing a run shows: one row per recording from its ``summary.json`` (frames, 3D
fraction, reprojection and held-out-view errors, suspects, handedness unless a fly, outputs), then
a sentence per recording on its held-out figures, the jobs' warnings, and the demo's truth line.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

# A Python warning ("file.py:12: UserWarning: text") or a logging record at WARNING level
# ("... WARNING name: text") in a job's log.
_WARNING = re.compile(r"(?:^|\s)(?:\w*Warning: |WARNING [\w.]+: )(?P<text>.+)$")


@dataclass(frozen=True)
class RunRecording:
    """What the table needs of a planned recording: its ``id`` (first column), ``outdir``
    (``summary.json``, ``logs/``) and whether it is the embedded ``demo`` (its truth comparison
    is printed last)."""

    id: str
    outdir: Path
    demo: bool = False


def _suspects(summary: dict) -> int | None:
    value = summary.get("suspects")
    if value is None:
        return None
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, (int, float)):
        return int(value)
    if isinstance(value, dict):
        for key in ("count", "total", "n"):
            if isinstance(value.get(key), (int, float)):
                return int(value[key])
        return sum(_suspects({"suspects": v}) or 0 for v in value.values())
    if isinstance(value, (list, tuple)):
        return len(value)
    return None


def log_warnings(outdir: Path) -> list[str]:
    """``"<log stem>: <message>"`` per distinct warning in ``<outdir>/logs/*.log``, in file
    order."""
    found: list[str] = []
    for log in sorted((Path(outdir) / "logs").glob("*.log")):
        try:
            lines = log.read_text(errors="replace").splitlines()
        except OSError:
            continue
        for line in lines:
            match = _WARNING.search(line)
            if match:
                found.append(f"{log.stem}: {match.group('text').strip()}")
    return list(dict.fromkeys(found))


#: The last line a stage script writes to its job's log when the stage returned; a signal that
#: stops it (SIGTERM, SIGINT, SIGHUP) ends the log with ``JOB_STOPPED`` and the signal's name, an
#: error with ``error: ...`` or a traceback. A log ending in none of these was cut off: its job
#: was killed (SIGKILL, out of memory).
JOB_FINISHED = "flylib: job finished"
JOB_STOPPED = "stopped by "


def job_end(log: Path) -> str:
    """How the job that wrote ``log`` ended: ``"finished"``, ``"failed"``, ``"stopped by SIG..."``
    or ``"killed"`` (its log ends without flylib's last line)."""
    try:
        lines = Path(log).read_text(errors="replace").strip().splitlines()
    except OSError:
        return "killed"
    last = lines[-1] if lines else ""
    if last == JOB_FINISHED:
        return "finished"
    if last.startswith(JOB_STOPPED):
        return last
    if last.startswith("error:") or "Error" in last:
        return "failed"
    return "killed"


def _unfinished(outdir: Path, since: float, signals: dict[str, str]) -> str | None:
    """What ended the recording's jobs in this (failed) run: a status for the table, naming the
    job and its log, or ``None`` when none of its jobs wrote a log since ``since``. ``signals``:
    log path -> the signal that ended its job, as Snakemake saw it (:func:`snakemake_report`)."""
    if not Path(outdir).is_dir():
        return "its output folder was deleted during the run; re-run to start it again"
    fresh = []
    for log in (Path(outdir) / "logs").glob("*.log"):
        try:
            if log.stat().st_mtime >= since:
                fresh.append((log.stat().st_mtime, log))
        except OSError:
            continue
    ends = [(log, job_end(log)) for _, log in sorted(fresh, reverse=True)]
    for wanted in ("failed", JOB_STOPPED, "killed"):
        for log, end in ends:
            if not end.startswith(wanted):
                continue
            if end == "failed":
                return f"failed: see {log}"
            if end == "killed":
                how = (
                    f"by {signals[str(log)]}"
                    if str(log) in signals
                    else "(SIGKILL or out of memory)"
                )
                return (
                    f"{log.stem} was killed {how}: its log {log} ends without an error; "
                    "re-run to resume"
                )
            return f"{log.stem} was {end}; re-run to resume"
    if ends:
        return (
            f"not finished: its last job ({ends[0][0].stem}) ended well, then the run "
            "stopped (see the warnings, or Snakemake's messages above); re-run to resume"
        )
    return None


# Snakemake's log: a job's process ended by a signal, then the job's error block naming its log.
_DIED = re.compile(r"died with <Signals\.(?P<signal>SIG\w+): \d+>")
_JOB_LOG = re.compile(r"^\s+log: (?P<log>.+?)(?: \(check log file)")


def snakemake_report(
    log: str | Path | Iterable[str | Path] | None,
) -> tuple[dict[str, str], list[str]]:
    """What Snakemake's own log file(s) of the run (what its ``onerror`` hook receives) say that
    no job log holds: ``(signals, warnings)``, job log path -> the signal that killed its job
    (``"SIGKILL"``), and the clock-skew errors (an output older than its input), one line each."""
    files = [log] if isinstance(log, (str, Path)) else list(log or [])
    signals: dict[str, str] = {}
    warnings: list[str] = []
    died = None
    for file in files:
        try:
            lines = Path(file).read_text(errors="replace").splitlines()
        except OSError:
            continue
        for line in lines:
            if (match := _DIED.search(line)) is not None:
                died = match.group("signal")
            elif died and (match := _JOB_LOG.match(line)) is not None:
                signals[match.group("log")] = died
                died = None
            if "clock skew" in line:
                warnings.append(" ".join(line.split()))
    return signals, list(dict.fromkeys(warnings))


def recording_row(
    rec: RunRecording, since: float | None = None, signals: dict[str, str] | None = None
) -> dict[str, Any]:
    """One table row: the recording's ``summary.json`` figures (``None`` where absent). With
    ``since`` (a failed run's start), a summary older than a log a job wrote since is an earlier
    run's: not shown, and ``unfinished`` says how the jobs ended and which log to read."""
    path = Path(rec.outdir) / "summary.json"
    row: dict[str, Any] = {
        "id": rec.id,
        "outdir": str(rec.outdir),
        "summary": None,
        "unfinished": None,
    }
    if since is not None:
        row["unfinished"] = _unfinished(rec.outdir, since, signals or {})
        if row["unfinished"] is not None and path.is_file() and path.stat().st_mtime >= since:
            row["unfinished"] = None  # assembled in this run: its jobs finished
        if row["unfinished"] is not None:
            return row
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return row
    error = summary.get("reprojection_error_px") or {}
    row.update(
        summary=summary,
        frames=summary.get("frames"),
        reconstructed=summary.get("reconstructed_3d_fraction"),
        median=error.get("median"),
        p95=error.get("p95"),
        suspects=_suspects(summary),
        accuracy=summary.get("accuracy"),
        truth=summary.get("error_vs_truth"),
        truth_before=summary.get("error_vs_truth_triangulation"),
        handedness=summary.get("handedness"),
    )
    return row


def handedness_cell(entry: dict | None) -> str:
    """The table's handedness cell: the score, and ``MIRRORED`` or ``?`` when the 3D is a mirror
    image or undetermined (:mod:`flylib.handedness`); ``-`` without one."""
    if not isinstance(entry, dict) or entry.get("verdict") is None:
        return "-"
    score = "-" if entry.get("score") is None else f"{float(entry['score']):+.2f}"
    if entry["verdict"] == "mirrored":
        return f"{score} MIRRORED"
    if entry["verdict"] == "undetermined":
        return f"{score} ?"
    return score


def _fmt(value: Any, kind: str) -> str:
    if value is None:
        return "-"
    if kind == "percent":
        return f"{100 * float(value):.1f}%"
    if kind == "px":
        return f"{float(value):.2f}"
    return str(value)


def _spread(median: Any, p95: Any) -> str:
    """A ``"median / p95"`` cell in px, as the held-out columns show theirs."""
    if median is None:
        return "-"
    return f"{_fmt(median, 'px')} / {_fmt(p95, 'px')}"


def _align(rows: Sequence[Sequence[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = []
    for r in rows:
        cells = [
            c.ljust(w) if i in (0, len(r) - 1) else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths))
        ]
        lines.append("  ".join(cells).rstrip())
    return lines


#: What the held-out-view error is, once under the table that shows it.
HELD_OUT_NOTE = (
    "held-out px = median / p95 distance from each camera's 2D to the 3D rebuilt without "
    "that camera, from the triangulation (tri) and the refined output (ref; lower is better, * the "
    "better method); reproj px (median / p95) only shows how closely the 3D fits the 2D it "
    "was built from"
)


def _held(block: dict | None) -> tuple[float, float] | None:
    figures = (block or {}).get("held_out_px") or {}
    if figures.get("median") is None:
        return None
    return float(figures["median"]), float(figures["p95"])


def held_out_cells(accuracy: dict | None) -> tuple[str, str]:
    """``(triangulation, output)`` cells ``"median / p95"`` of the held-out-view error, the better
    (lower median, then p95) marked ``*``; ``"-"`` where absent."""
    if not accuracy:
        return "-", "-"
    tri = _held(accuracy.get("triangulation"))
    out = _held(accuracy.get("output")) if accuracy.get("output_stage") == "refinement" else None
    cells = [f"{v[0]:.2f} / {v[1]:.2f}" if v else "-" for v in (tri, out)]
    if tri and out and out != tri:
        better = 1 if out <= tri else 0
        cells[better] += " *"
    return cells[0], cells[1]


def accuracy_line(rec_id: str, accuracy: dict) -> str | None:
    """One sentence a biologist can act on: is the refined 3D better than the plain triangulation
    by the held-out-view error, which points keep the triangulation and why, and which camera (if
    any) disagrees with the others."""
    tri = _held(accuracy.get("triangulation"))
    refined = accuracy.get("output_stage") == "refinement"
    if tri is None:  # held out, a camera leaves a point in at least 2 others
        return (
            f"{rec_id}: no held-out error: no point is seen by 3 cameras, so none can be rebuilt "
            "without one of them and checked against it; the images cannot measure the 3D's error"
            + (
                ", nor refinement's: the results keep the triangulation for every point"
                if refined
                else ""
            )
        )
    evaluated, total = accuracy.get("frames_evaluated", 0), accuracy.get("frames_total", 0)
    frames = f" Held out on {evaluated} of {total} frames." if evaluated < total else ""
    figures = f"median {tri[0]:.2f} px, p95 {tri[1]:.2f} px"
    if not refined:
        line = f"{rec_id}: each camera is predicted from the others to {figures} (triangulation)."
    else:
        out = _held(accuracy.get("output")) or tri
        raw = _held(accuracy.get("refinement")) or tri
        per_point = (accuracy.get("output") or {}).get("per_point") or {}
        checked = {k for k, v in per_point.items() if v.get("n")}
        kept = [k for k in accuracy.get("kept_triangulation") or [] if k in checked]
        unchecked = [k for k in per_point if k not in checked]
        compare = (
            f"held-out median {tri[0]:.2f} -> {out[0]:.2f} px, p95 {tri[1]:.2f} -> {out[1]:.2f} px"
        )
        if accuracy.get("kept_everywhere"):
            line = (
                f"{rec_id}: refinement made this recording worse than triangulation (held-out "
                f"median {tri[0]:.2f} -> {raw[0]:.2f} px, p95 {tri[1]:.2f} -> {raw[1]:.2f} px), "
                "so the results keep the triangulation for every point. Its assumptions (smooth "
                "motion, constant bone lengths, a still thorax) do not fit this fly or this rig: "
                "check the rig first (the bundle-adjustment warning, or a calibration file), "
                "or set pipeline.do_refinement: false."
            )
        elif kept:
            line = (
                f"{rec_id}: the refined 3D is used for {len(checked) - len(kept)} of the "
                f"{len(checked)} points that could be checked ({compare}); for {len(kept)} "
                f"({_named(kept)}) it predicted the held-out cameras worse than triangulation, "
                "so the results keep their triangulation (flag kept_triangulation in "
                "stages/refinement.h5)."
            )
        else:
            line = f"{rec_id}: refinement is better than triangulation ({compare}); the results use it."
        if unchecked and not accuracy.get("kept_everywhere"):
            line += (
                f" {len(unchecked)} points ({_named(unchecked)}) are never seen by three "
                "cameras at once: no held-out camera checks them."
            )
    return (
        line + frames + _worst_view(accuracy.get("output") or accuracy.get("triangulation"), tri[0])
    )


def _named(points: list[str]) -> str:
    return ", ".join(points[:6]) + (f" and {len(points) - 6} more" if len(points) > 6 else "")


def _worst_view(block: dict, overall: float) -> str:
    """Cameras whose held-out error is over twice the typical (better-half median) camera's:
    named, with the fix. (Three cameras see each side, so one camera's error shows in all three.)"""
    views = {
        name: v["median"]
        for name, v in ((block or {}).get("per_view") or {}).items()
        if v.get("median") is not None
    }
    if len(views) < 3:
        return ""
    # the better half: a mis-calibrated camera drags its whole side (half the views) up
    values = np.sort(list(views.values()))
    typical = float(np.median(values[: max(1, len(values) // 2)]))
    bad = [name for name, value in views.items() if value > 2 * typical]
    if not bad:
        return ""
    figures = ", ".join(f"{name} {views[name]:.2f} px" for name in bad)
    return (
        f" Cameras {figures} disagree with the others (typical {typical:.2f} px held out): "
        "one of them is mis-calibrated or mislabeled (its footage or 2D from another camera); "
        "check the rig and which video is which camera."
    )


def truth_line(rec_id: str, error: dict, before: dict | None = None) -> str:
    """The demo's 3D error against its truth, as one line; with ``before`` (the triangulation's
    error when the refinement stage ran) that figure follows."""
    line = (
        f"{rec_id}: 3D error against the demo truth: median {error['median']:.4f}, "
        f"p95 {error['p95']:.4f} world units (body length {error['body_length']:.2f}); "
        f"after similarity alignment median {error['median_aligned']:.4f}; "
        f"{100 * error['reconstructed']:.1f}% of points reconstructed"
    )
    if before:
        line += (
            f" (refined 3D; triangulation alone: median {before['median']:.4f}, "
            f"p95 {before['p95']:.4f}, aligned {before['median_aligned']:.4f})"
        )
    return line


def run_table(
    recordings: Iterable[RunRecording],
    *,
    failed: bool = False,
    since: float | None = None,
    snakemake_log: str | Path | Iterable[str | Path] | None = None,
) -> str:
    """The end-of-run report: the table, warnings, then the demo's truth line. ``failed``: the
    run ended with an error; ``since``: when it started (:func:`recording_row`);
    ``snakemake_log``: its log file(s), for the signal that killed a job and clock-skew errors."""
    recordings = list(recordings)
    signals, skew = snakemake_report(snakemake_log)
    rows = [recording_row(rec, since if failed else None, signals) for rec in recordings]
    with_suspects = any(r.get("suspects") is not None for r in rows)
    with_accuracy = any(r.get("accuracy") for r in rows)
    # narrow enough for a 100-column terminal: each error is one "median / p95" cell
    header = ["recording", "frames", "in 3D", "reproj px"]
    # a fly needs no column: it appears when a 3D is a mirror image or undetermined
    with_handedness = any(
        (r.get("handedness") or {}).get("verdict") not in (None, "right-handed") for r in rows
    )
    if with_accuracy:
        header += ["held-out tri", "held-out ref"]
    if with_suspects:
        header.append("suspects")
    if with_handedness:
        header.append("handedness")
    header.append("outputs")
    cells = [header]
    for r in rows:
        if r["summary"] is None:
            status = "no result"
            if r["unfinished"] is not None:
                status = r["unfinished"]
            elif failed:
                status = "no result yet: see logs/"
            line = (
                [r["id"], "-", "-", "-"]
                + (["-", "-"] if with_accuracy else [])
                + (["-"] if with_suspects else [])
                + (["-"] if with_handedness else [])
                + [f"{r['outdir']}  ({status})"]
            )
        else:
            line = [
                r["id"],
                _fmt(r["frames"], "int"),
                _fmt(r["reconstructed"], "percent"),
                _spread(r["median"], r["p95"]),
            ]
            if with_accuracy:
                line += list(held_out_cells(r.get("accuracy")))
            if with_suspects:
                line.append(_fmt(r["suspects"], "int"))
            if with_handedness:
                line.append(handedness_cell(r.get("handedness")))
            line.append(r["outdir"])
        cells.append(line)
    title = "flylib: per-recording results" + (
        " (the run failed; rows without a result did not finish)" if failed else ""
    )
    lines = [title, *_align(cells)]
    sentences = [accuracy_line(r["id"], r["accuracy"]) for r in rows if r.get("accuracy")]
    sentences = [s for s in sentences if s]
    if sentences:
        lines += [f"accuracy: {HELD_OUT_NOTE}:", *(f"  {s}" for s in sentences)]
    mirror = [(r.get("handedness") or {}).get("message") for r in rows]
    if any(mirror):
        lines += [
            "mirror image (the left legs on the fly's right):",
            *(f"  {r['id']}: {m}" for r, m in zip(rows, mirror) if m),
        ]
    warnings = [  # assemble's warning of a mirror image is the line above
        f"  {rec.id}: {w}"
        for rec, m in zip(recordings, mirror)
        for w in log_warnings(rec.outdir)
        if not (m and m in w)
    ]
    warnings += [f"  snakemake: {w}" for w in skew]
    if warnings:
        lines += ["warnings:", *warnings]
    lines += [
        truth_line(r["id"], r["truth"], r.get("truth_before"))
        for rec, r in zip(recordings, rows)
        if rec.demo and r.get("truth")
    ]
    return "\n".join(lines)
