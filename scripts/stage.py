#!/usr/bin/env python
"""Run a stage that has no script of its own: ``run_<stage>(inputs, **files)`` of its home
``flylib.pipeline.<stage>``, each file by its name in the stage's rule (its rule's
``script: "../../scripts/stage.py"``). By hand: --rule STAGE --config FILE --file NAME=PATH
for each of the rule's named inputs and outputs."""

from pathlib import Path

from _cli import run_script, script_main, script_parser


def _named_files(job) -> dict[str, Path | list[Path]]:
    """The job's named input and output files, by name (a list where a name has several)."""
    files: dict[str, Path | list[Path]] = {}
    for part in (job.input, job.output):
        for name in part.keys():
            value = part[name]
            files[name] = Path(value) if isinstance(value, str) else [Path(v) for v in value]
    return files


def main(argv=None, *, job=None) -> int:
    from flylib.stages import run_function

    parser = script_parser(__doc__)
    parser.add_argument("--rule", dest="rule_name", help="the stage to run (by hand)")
    parser.add_argument(
        "--file",
        dest="named_files",
        action="append",
        default=[],
        metavar="NAME=PATH",
        help="one of the rule's files by its name (by hand; once per file)",
    )
    stage = job.rule if job is not None else parser.parse_known_args(argv)[0].rule_name
    if stage is None:
        parser.error("the following arguments are required: --rule")

    def run(inputs, rule_name=None, named_files=(), **files):
        given = dict(text.split("=", 1) for text in named_files)
        return run_function(stage)(inputs, **files, **{k: Path(v) for k, v in given.items()})

    return script_main(
        parser,
        run,
        argv,
        job=job,
        stage=stage,
        outdir=lambda given: getattr(job.wildcards, "outdir", None) if job else None,
        job_extra=_named_files,
    )


if __name__ == "__main__":
    run_script(main, globals())
