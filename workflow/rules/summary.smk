# The end of every run: one line per recording (frames, fraction reconstructed,
# reprojection error, suspects when counted, where the outputs are), the warnings the
# jobs logged (and Snakemake's clock-skew errors), and the demo's error against its
# truth last. A recording whose jobs did not finish says how they ended: failed (see
# its log), stopped by a signal, or killed (a log cut off before flylib's last line).
# Printed on success and on error alike (not for dry runs), at exit, so that it follows Snakemake's own closing
# lines ("Complete log", "Elapsed time") and is the last thing on screen. A run with
# nothing to do calls neither hook (Snakemake returns before them): it prints the
# table of the existing results, after Snakemake's "Nothing to be done".

import atexit
import logging
import time

from snakemake.common import NOTHING_TO_BE_DONE_MSG

from flylib.run_summary import RunRecording, run_table
from flylib.sessions import session_lines

_RUN_START = time.time()
_RUN_RECORDINGS = [RunRecording(r.id, r.outdir, r.demo) for r in RECORDINGS if r.id not in SKIPPED]


_TABLE_STATE = {"printed": False, "nothing_to_do": False}


def _print_run_table(failed: bool, snakemake_log=None) -> None:
    _TABLE_STATE["printed"] = True
    text = run_table(_RUN_RECORDINGS, failed=failed, since=_RUN_START, snakemake_log=snakemake_log)
    text = "\n".join(
        [text, *session_lines(SESSIONS)]
    )  # session calibration: its rig vs each trial's
    atexit.register(lambda: print("\n" + text, file=sys.stderr, flush=True))


class _NothingToDo(logging.Handler):
    """Notes Snakemake's "Nothing to be done" (logged by a real run and a dry run alike)."""

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage() == NOTHING_TO_BE_DONE_MSG:
            _TABLE_STATE["nothing_to_do"] = True


def _table_after_nothing_to_do() -> None:
    if _TABLE_STATE["printed"] or not _TABLE_STATE["nothing_to_do"] or workflow.dryrun:
        return
    text = "\n".join([run_table(_RUN_RECORDINGS), *session_lines(SESSIONS)])
    print("\nflylib: nothing to do; the existing results:\n" + text, file=sys.stderr, flush=True)


if workflow.is_main_process:
    logging.getLogger("snakemake.logging").addHandler(_NothingToDo(logging.INFO))
    atexit.register(_table_after_nothing_to_do)


onsuccess:
    _print_run_table(failed=False, snakemake_log=log)


onerror:
    _print_run_table(failed=True, snakemake_log=log)
