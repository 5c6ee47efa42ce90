"""Options shared by ``figures`` and ``report``: output folder, seeds, horizon."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import InputError
from ..studies import StudyConfig
from .options import positive_int


def add_study_options(parser: argparse.ArgumentParser, out_help: str) -> None:
    parser.add_argument("--out", required=True, metavar="DIR", help=out_help)
    parser.add_argument("--seeds", type=positive_int, default=20, metavar="S", help="run seeds 0..S-1 (default 20)")
    parser.add_argument("--steps", type=positive_int, metavar="K", help="horizon in ticks (default: the scenarios')")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def study_config(args: argparse.Namespace) -> StudyConfig:
    return StudyConfig(seeds=args.seeds, steps=args.steps, quiet=args.quiet or not sys.stderr.isatty())


def out_dir(text: str) -> Path:
    """The output folder, created; a path that cannot be one is bad input."""
    path = Path(text)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError("out", f"cannot create folder {text}: {e.strerror or e}") from None
    return path
