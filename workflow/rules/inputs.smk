# Input functions that tell the demo (its files come from the demo rule) from a real
# recording (its files are on disk): they use DEMO* from demo.smk, included above.


def recording_inputs(wildcards) -> list[str]:
    """What pose2d reads: the footage and the files imported 2D comes from (for the
    demo, everything the demo rule writes), so an edit of any re-runs pose2d."""
    if unplanned(wildcards):
        return unplanned(wildcards)
    rec = recording(wildcards)
    if rec.demo:
        return DEMO_OUTPUTS
    # the import files as the run's preflight found them (load_run_config), not again
    return [str(f) for f in [*rec.footage, *(rec.import_files or ())]]


def footage_inputs(wildcards) -> list[str]:
    """The recording's footage files (for the demo, the videos the demo rule writes)."""
    if unplanned(wildcards):
        return unplanned(wildcards)
    rec = recording(wildcards)
    if rec.demo:
        return DEMO_FOOTAGE
    return [str(f) for f in rec.footage]


def assemble_inputs(wildcards) -> dict:
    if unplanned(wildcards):
        return {"unplanned": unplanned(wildcards)}
    # pose2d's artifact is read even with pose2d off (made by an earlier run)
    files = {s: artifact(s) for s in ARTIFACTS if s == "pose2d" or FLAGS[s]}
    files = {k: v.format(outdir=wildcards.outdir) for k, v in files.items()}
    if FLAGS["bundle_adjustment"]:
        files["bundle_adjustment"] = rig_artifact(wildcards)
    files["calibration"] = calibration_inputs(wildcards)
    if recording(wildcards).demo:
        files["truth"] = DEMO_TRUTH
    return files
