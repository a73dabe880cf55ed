#!/usr/bin/env bash
# Set up flylib in ./.venv: a virtual environment with the package (editable) and its
# test extra. Safe to re-run: a second run only checks that everything is in place.
#
#   FLYLIB_PYTHON   interpreter to build the venv from (default: python3, needs >= 3.11)
#   FLYLIB_TORCH    pip requirement for PyTorch (default: the CPU build torch==2.13.0 on
#                   machines without an NVIDIA GPU, plain "torch" where nvidia-smi sees one)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

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
   || [ pyproject.toml -nt .venv/.flylib-installed ]; then
  echo "install.sh: installing flylib and its dependencies into .venv"
  "${pip[@]}" install -e ".[test]"
  touch .venv/.flylib-installed
fi
echo "install.sh: ready ($(.venv/bin/python -c 'import flylib, torch, jax; print(f"flylib {flylib.__version__}, torch {torch.__version__}, jax {jax.__version__}")'))"
