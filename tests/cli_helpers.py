"""Calling the CLI in-process from tests."""
from __future__ import annotations

import json

from diskf_mesh.cli import main as cli
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.data.trace import trace_to_json


def run_cli(argv, capsys):
    """(exit status, stdout, stderr) of ``diskf-mesh argv``; argparse's own
    errors arrive as SystemExit, the commands' as a return value."""
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


def simulated_doc(steps=20, seed=1, topology="ring") -> dict:
    """A small valid diskf-trace/1 document from the shipped scenario."""
    scn = load_scenario("quadrants").with_overrides(topology=topology, steps=steps)
    return trace_to_json(simulate(scn, [seed]))


def write(path, doc) -> str:
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return str(path)
