"""``diskf-mesh figures``: every figure of the report as PNG files.

The scenarios (Scenario 2 with its links), 2-D trajectories of every
estimator against the truth, input estimates per node, x and y against
time, error against communication range, the range-120 / all-to-all bars,
the observation-window variants and the isolated-sensor diagnosis.
"""
from __future__ import annotations

import argparse

from ..figures import make_figures
from .options import add_command
from .study_options import add_study_options, out_dir, study_config


def register(subparsers) -> None:
    p = add_command(subparsers, "figures", "write every figure of the report (PNG)", __doc__)
    add_study_options(p, "folder for the PNG files (created)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = out_dir(args.out)
    paths = make_figures(study_config(args), out)
    print(f"{len(paths)} figures -> {out}")
    return 0
