"""What ``figures`` and ``report`` share: options (output folder, seeds,
horizon, quiet) and the command skeleton around one action."""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from diskf_mesh.core.errors import InputError
from diskf_mesh.cli.options import add_command, add_ticks, check_output_dir, positive_int


PLOTTING = ("matplotlib", "PIL")  # pyproject.toml's figures extra
INSTALL_FIGURES = "pip install '.[figures]'"  # from a clone, as the README installs


def add_study_command(subparsers, name: str, summary: str, doc: str, out_help: str, action) -> None:
    """A subcommand running ``action(config, out_dir) -> message``."""
    p = add_command(subparsers, name, summary, doc)
    p.add_argument("--out", required=True, metavar="DIR", help=out_help)
    p.add_argument("--seeds", type=positive_int, default=20, metavar="S", help="run seeds 0..S-1 (default 20)")
    add_ticks(p, help="horizon in ticks (default: the scenarios')")
    p.add_argument("--quiet", action="store_true", help="no progress (a bar on a terminal, else a line per stage)")
    p.set_defaults(func=lambda args: run_study(args, action))


def run_study(args: argparse.Namespace, action) -> int:
    from diskf_mesh.studies.suite import StudyConfig  # here, not at the top: --help loads every command module

    terminal = sys.stderr.isatty()
    cfg = StudyConfig(seeds=args.seeds, steps=args.ticks, quiet=args.quiet or not terminal,
                      lines=not args.quiet and not terminal)
    print(drawing(args.command, lambda: action(cfg, out_dir(args.out))))
    return 0


def drawing(command: str, draw):
    """``draw()``; ``InputError`` saying how to install the plotting
    packages (as the README does) if they are not installed, found before
    ``draw`` writes anything."""
    try:
        for name in PLOTTING:
            importlib.import_module(name)
        return draw()
    except ModuleNotFoundError as e:
        if (e.name or "").split(".")[0] not in PLOTTING:
            raise
        raise InputError(command, f"needs {e.name}, which diskf-mesh installs only with its figures extra: "
                                  f"{INSTALL_FIGURES} in the diskf-mesh folder") from None


def out_dir(text: str) -> Path:
    """The output folder, created; a path that cannot be one is bad input."""
    return check_output_dir(text, "out")
