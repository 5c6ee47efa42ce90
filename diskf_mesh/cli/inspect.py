"""``diskf-mesh inspect RUN.mcap``: what a recording holds.

Prints the run (scenario, estimator, seed, faults, versions), whether the
file is whole (MCAP's CRCs, summary and footer, the run's result, every
planned tick; a recording cut short or damaged is read up to its last whole
tick), the run's verdict as its own check recorded it (not re-checked:
``--check`` re-checks it on the engine, as ``replay`` does), the agents
and their reports, the messages sent and what became of them at each
linked receiver (fused, lost, late, rejected and why, duplicate copies),
and the metrics of the recorded estimates. ``--json`` prints the same as
one JSON document.
"""
from __future__ import annotations

import argparse
import json

from diskf_mesh.cli.options import add_command, json_safe


def register(subparsers) -> None:
    p = add_command(subparsers, "inspect", "summarise an MCAP recording (up --record)", __doc__)
    p.add_argument("recording", metavar="RUN.mcap", help="a recording of diskf-mesh up/world --record")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--check", action="store_true", help="re-check the run's verdict on the engine (as replay does) "
                   "instead of printing the one the run recorded")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from diskf_mesh.recording.reader import read
    from diskf_mesh.recording.summary import format_summary, summary

    s = summary(read(args.recording), recheck=args.check)
    print(json.dumps(json_safe(s), indent=1) if args.json else format_summary(s))
    return 0
