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


# ``pytest -m quick``: the unit tests of every layer, none that starts processes (``mesh``) or is ``slow``:
# a few minutes on two cores (docs/costs.md#tests-quick); CI runs every test
QUICK = {"test_equations.py", "test_filters.py", "test_linalg_fast.py", "test_layers.py", "test_inputs.py",
         "test_input_models.py", "test_cli.py", "test_vocabulary.py", "test_provenance.py", "test_string_ids.py",
         "test_replay.py", "test_world_machine.py", "test_agent_machine.py", "test_guard.py", "test_mesh_wire.py",
         "test_shell.py", "test_no_narrative.py", "test_plugins.py", "test_verify.py", "test_formats.py",
         "test_faults.py", "test_oracle.py", "test_api.py", "test_readme.py", "test_costs.py"}


def pytest_collection_modifyitems(config, items):
    import pytest

    for item in items:
        if item.path.name in QUICK and not any(item.get_closest_marker(m) for m in ("mesh", "slow", "docker")):
            item.add_marker(pytest.mark.quick)
