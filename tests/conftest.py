"""The processes the tests start (``python -m sim.launcher ...``) import the
repository's ``sim`` and ``agents`` from wherever they run: the checkout's
root goes first on their PYTHONPATH (an installed diskf_mesh carries them
inside the package, and ``diskf_mesh.cli`` finds them there)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = str(Path(__file__).resolve().parents[1])
_paths = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
if ROOT not in _paths:
    os.environ["PYTHONPATH"] = os.pathsep.join([ROOT, *_paths])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
