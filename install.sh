#!/usr/bin/env bash
# Set up flylib in ./.venv: a virtual environment with the package (editable) and its
# test extra. Safe to re-run: a second run only checks that everything is in place.
#
#   FLYLIB_PYTHON   interpreter to build the venv from (default: python3, needs >= 3.11)
#   FLYLIB_TORCH    pip requirement for PyTorch (default: the CPU build torch==2.13.0 on
#                   machines without an NVIDIA GPU, plain "torch" where nvidia-smi sees one)
#
#   bash install.sh --test-system-packages
#                   also install the system packages two tests use, where that is possible
#                   (root and apt-get): slurm-wlm and munge (a real single-node SLURM,
#                   tests/workflow/test_slurm.py), chromium and chromium-driver (tests/gui/test_browser.py).
#                   Quiet; where they cannot be installed it says so in one line and goes
#                   on (those tests then skip with the reason). .ci/run passes it.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

system_packages=(slurm-wlm munge chromium chromium-driver)
install_system_packages() {
  local missing=()
  command -v slurmctld >/dev/null 2>&1 && command -v munged >/dev/null 2>&1 || missing+=(slurm-wlm munge)
  command -v chromedriver >/dev/null 2>&1 || missing+=(chromium chromium-driver)
  [ ${#missing[@]} -eq 0 ] && return 0
  if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "install.sh: not installing ${missing[*]} (needs root and apt-get); the tests that use them skip"
    return 0
  fi
  echo "install.sh: installing system packages ${missing[*]}"
  local apt=(env DEBIAN_FRONTEND=noninteractive timeout 900 apt-get -qq -y --no-install-recommends)
  if ! "${apt[@]}" install "${missing[@]}" >/dev/null 2>&1; then
    timeout 300 apt-get -qq update >/dev/null 2>&1 || true
    "${apt[@]}" install "${missing[@]}" >/dev/null 2>&1 \
      || echo "install.sh: could not install ${missing[*]} with apt-get; the tests that use them skip"
  fi
}
for arg in "$@"; do
  case $arg in
    --test-system-packages) install_system_packages ;;
    *) echo "install.sh: unknown option $arg (known: --test-system-packages)" >&2; exit 2 ;;
  esac
done

python=${FLYLIB_PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$python" -m venv .venv
fi
pip=(.venv/bin/python -m pip --disable-pip-version-check -q)

if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  if [ -n "${FLYLIB_TORCH:-}" ]; then
    torch_req=$FLYLIB_TORCH
  elif command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    torch_req=torch
  else
    # No GPU: pin the CPU build so the install never pulls multi-GB CUDA wheels.
    torch_req=torch==2.13.0
  fi
  echo "install.sh: installing PyTorch ($torch_req)"
  "${pip[@]}" install "$torch_req"
fi

if ! .venv/bin/python -c "import flylib, snakemake, jax, av, pytest" 2>/dev/null \
   || [ pyproject.toml -nt .venv/.flylib-installed ] || [ envs/flylib.yaml -nt .venv/.flylib-installed ]; then
  echo "install.sh: installing flylib and its dependencies into .venv"
  # the dependencies at the versions the tests ran with (envs/flylib.yaml's pins; torch is
  # chosen above), so a new upstream release cannot change what a fresh install gets
  constraints=$(mktemp)
  sed -n 's/^ *- \([A-Za-z0-9_.-]*==[^ ]*\)$/\1/p' envs/flylib.yaml | grep -v '^torch==' >"$constraints"
  "${pip[@]}" install -c "$constraints" -e ".[test]"
  rm -f "$constraints"
  touch .venv/.flylib-installed
fi
echo "install.sh: ready ($(.venv/bin/python -c 'import flylib, torch, jax; print(f"flylib {flylib.__version__}, torch {torch.__version__}, jax {jax.__version__}")'))"
