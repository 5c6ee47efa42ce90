"""``diskf-mesh report``: run every experiment and write the markdown report.

Writes DIR/reproduction.md (tables beside the paper's numbers, figures,
the differences and where DISKF is not the best), DIR/figures/*.png and
DIR/results.json (every number). ``--out docs`` regenerates the committed
docs/reproduction.md.
"""
from __future__ import annotations

import argparse

from ..report import write_report
from .options import add_command
from .study_options import add_study_options, out_dir, study_config


def register(subparsers) -> None:
    p = add_command(subparsers, "report", "run every experiment, write the markdown report", __doc__)
    add_study_options(p, "folder for reproduction.md, figures/ and results.json (created)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = out_dir(args.out)
    paths = write_report(study_config(args), out)
    print(f"report -> {paths[0]} ({len(paths) - 2} figures, numbers in {paths[1]})")
    return 0
