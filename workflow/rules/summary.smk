# The end of every run: one line per recording (frames, fraction reconstructed,
# reprojection error, suspects when counted, where the outputs are), the warnings the
# jobs logged, and the demo's error against its truth last. Printed on success and on
# error alike (not for dry runs), at exit, so that it follows Snakemake's own closing
# lines ("Complete log", "Elapsed time") and is the last thing on screen.

import atexit
import time

from flylib.run_summary import RunRecording, run_table

_RUN_START = time.time()
_RUN_RECORDINGS = [RunRecording(r.id, r.outdir, r.demo) for r in RECORDINGS if r.id not in SKIPPED]


def _print_run_table(failed: bool) -> None:
    text = run_table(_RUN_RECORDINGS, failed=failed, since=_RUN_START)
    atexit.register(lambda: print("\n" + text, file=sys.stderr, flush=True))


onsuccess:
    _print_run_table(failed=False)


onerror:
    _print_run_table(failed=True)
