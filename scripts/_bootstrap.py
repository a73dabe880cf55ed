"""Make ``import flylib`` work for a script run from a checkout without installing it
(e.g. inside a per-rule conda environment that carries only the dependencies)."""

import importlib.util
import sys
from pathlib import Path

if importlib.util.find_spec("flylib") is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
