# Manual corrections (flylib gui): a recording's corrections.h5 sidecar, when it
# exists, is an input of its triangulation job, so saving corrections re-runs exactly
# triangulation, assemble and visualization for that recording (pose2d and bundle
# adjustment stay). The sidecar is looked up when the DAG is built: an input function
# returns it only if it exists. The config's `corrections` key may name another file
# (path template with {outdir}, {recording}, {id}, {name}; relative to the outdir).

from flylib.corrections import corrections_path as _corrections_path


def _find_corrections() -> dict[str, str]:
    """``outdir -> sidecar`` of every recording that has corrections."""
    found = {}
    named_missing = []
    for rec in RECORDINGS:
        try:
            path, named = _corrections_path(
                CONFIG.data.get("corrections"), rec.outdir, rec.path, rec.id
            )
        except FlylibError as exc:
            stop_run(str(exc))
        if path.is_file():
            found[str(rec.outdir)] = str(path)
        elif named:
            named_missing.append(f"{rec.id}: {path}")
    if named_missing:
        logger.warning(
            "corrections: no such file for "
            + "; ".join(named_missing)
            + " (those recordings are triangulated without manual corrections)"
        )
    return found


CORRECTIONS = _find_corrections()


def corrections_inputs(wildcards) -> dict:
    """``{"corrections": sidecar}`` for a recording that has one, else nothing."""
    path = CORRECTIONS.get(wildcards.outdir)
    return {"corrections": path} if path else {}
