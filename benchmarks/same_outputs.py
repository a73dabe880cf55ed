"""A refactor changes no result: the demo and the DeepFly3D sample run through the
workflow by this checkout and by ``--baseline DIR`` (``git worktree add /tmp/base REV``),
then every output compared.

Compared: each HDF5 file's datasets (values, dtype, shape) and attributes, the stored
``params_sha256`` of every stage among them; ``summary.json`` without its times; every
other file byte for byte (logs, Snakemake's benchmark files and the run's lock left
out). Last, this checkout plans (``snakemake -n``) over the baseline's output folders:
an unchanged result is "Nothing to be done".

    python benchmarks/same_outputs.py --baseline /tmp/base [--work /tmp/same]

Exit status 1 when anything differs. The sample needs ``../shared/data`` beside the
checkout; without it only the demo is compared.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO.parent / "shared" / "data" / "deepfly3d-sample"
BIN = Path(sys.executable).parent
_CLOCK = ("time", "second", "created", "date")
#: Per-write identities: random ids, and the run's own folder (replaced by ``<work>``).
_IDENTITY = ("artifact_id", "upstream_artifact_ids")


def _env(checkout: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(checkout / "src")}


def _run(checkout: Path, work: Path, *args: str) -> subprocess.CompletedProcess:
    command = [str(BIN / "snakemake"), "-s", str(checkout / "Snakefile"), "-d", str(work)]
    return subprocess.run(
        [*command, *args], env=_env(checkout), capture_output=True, text=True, check=False
    )


def _cases(work: Path) -> dict[str, list[str]]:
    """Each case's work folder, made ready, and its extra snakemake arguments."""
    cases = {"demo": []}
    if SAMPLE.is_dir():
        (work / "sample.yaml").write_text(
            json.dumps(
                {
                    "recordings": [
                        {
                            "path": str(SAMPLE),
                            "import": {"format": "deepfly3d", "files": "df3d_result_2d.pkl"},
                        }
                    ],
                    "outdir": "sample_outputs/{id}",
                }
            )
        )
        cases["sample"] = ["--configfile", str(work / "sample.yaml")]
    return cases


def _untimed(value, work: str = ""):
    if isinstance(value, dict):
        return {
            k: _untimed(v, work)
            for k, v in value.items()
            if k not in _IDENTITY and not any(c in k for c in _CLOCK)
        }
    if isinstance(value, list):
        return [_untimed(v, work) for v in value]
    return value.replace(work, "<work>") if isinstance(value, str) and work else value


def _attr(value, work: str):
    if isinstance(value, bytes):
        value = value.decode()
    while isinstance(value, str):  # JSON, sometimes JSON in JSON
        try:
            value = json.loads(value)
        except ValueError:
            return value.replace(work, "<work>")
    return _untimed(value, work) if isinstance(value, (dict, list)) else np.asarray(value).tolist()


def _hdf5(path: Path, work: str) -> dict:
    def attrs(obj) -> dict:
        return {k: _attr(v, work) for k, v in obj.attrs.items() if not any(c in k for c in _CLOCK)}

    content = {}
    with h5py.File(path, "r") as f:

        def visit(name, obj):
            content[f"{name}@attrs"] = attrs(obj)
            if isinstance(obj, h5py.Dataset):
                content[name] = (str(obj.dtype), obj.shape, np.asarray(obj[()]).tobytes())

        content["/@attrs"] = attrs(f)
        f.visititems(visit)
    return content


def outputs(root: Path) -> dict:
    """Every output below ``root``, as compared (``root`` itself written ``<work>``)."""
    found, work = {}, str(root)
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if not path.is_file() or {"logs", "benchmarks", ".snakemake"} & set(rel.parts):
            continue
        if path.name.startswith(".flylib") or path.suffix == ".lock":
            continue
        if path.suffix == ".h5":
            found[str(rel)] = _hdf5(path, work)
        elif path.name in ("summary.json", "session_summary.json"):
            found[str(rel)] = _untimed(json.loads(path.read_text()), work)
        else:
            found[str(rel)] = path.read_bytes()
    return found


def _differences(a: dict, b: dict, where: str = "") -> list[str]:
    lines = [f"{where}{k}: only in this checkout" for k in a.keys() - b.keys()]
    lines += [f"{where}{k}: only in the baseline" for k in b.keys() - a.keys()]
    for key in sorted(a.keys() & b.keys()):
        if isinstance(a[key], dict) and isinstance(b[key], dict):
            lines += _differences(a[key], b[key], f"{where}{key} / ")
        elif a[key] != b[key]:
            lines.append(f"{where}{key}: differs")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", type=Path, required=True, help="the checkout before")
    parser.add_argument("--work", type=Path, default=Path("/tmp/flylib-same-outputs"))
    parser.add_argument(
        "--keep-baseline", action="store_true", help="reuse the baseline's outputs of --work"
    )
    args = parser.parse_args()
    checkouts = {"this": REPO, "baseline": args.baseline.resolve()}
    found, failed = {}, False
    for name, checkout in checkouts.items():
        work = args.work / name
        if name == "baseline" and args.keep_baseline and work.is_dir():
            found[name] = outputs(work)
            continue
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        for case, extra in _cases(work).items():
            proc = _run(checkout, work, "--cores", "2", *extra)
            if proc.returncode:
                print(f"{name} {case}: snakemake failed\n{proc.stderr[-3000:]}")
                return 1
        found[name] = outputs(work)
        print(f"{name}: {len(found[name])} output files")
    for line in _differences(found["this"], found["baseline"]):
        print(line)
        failed = True
    # the baseline's folders, planned by this checkout: nothing to re-run
    base = args.work / "baseline"
    for case, extra in _cases(base).items():
        proc = _run(REPO, base, "-n", *extra)
        if "Nothing to be done" not in proc.stdout + proc.stderr:
            print(f"{case}: this checkout would re-run jobs in the baseline's outputs:")
            print((proc.stdout + proc.stderr)[-3000:])
            failed = True
        else:
            print(f"{case}: the baseline's outputs planned by this checkout: Nothing to be done")
    print("DIFFERENT" if failed else "SAME: every output and params hash equal")
    return int(failed)


if __name__ == "__main__":
    sys.exit(main())
