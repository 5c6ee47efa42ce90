"""Options and output shared by the subcommands.

Option values are checked by argparse ``type=`` callables, so a bad value
ends as argparse's one line ``error: argument --X: ...`` with status 2
before any work is done. Output paths are checked with ``check_output``
before any work, and written with ``save_json`` (``diskf_mesh.outputs``:
atomic, the user's umask, ``-`` for standard output).
"""
from __future__ import annotations

import argparse
import math
from dataclasses import replace

from .. import algorithms
from ..errors import InputError
from ..model import COMPENSATION_FORMS, Params
from ..outputs import check_output, check_output_dir, human_stream, json_safe, save_json  # noqa: F401 (re-exported)


def _integer(text: str, low: int, what: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = low - 1
    if v < low:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return v


def positive_int(text: str) -> int:
    return _integer(text, 1, "a positive integer")


def seed_value(text: str) -> int:
    return _integer(text, 0, "a non-negative integer")


def _non_negative(text: str, finite: bool) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if math.isnan(v) or v < 0 or (finite and math.isinf(v)):
        kind = "a finite non-negative number" if finite else "a non-negative number (or inf)"
        raise argparse.ArgumentTypeError(f"must be {kind}, got {text!r}")
    return v


def range_value(text: str) -> float:
    """Communication radius: >= 0, ``inf`` allowed."""
    return _non_negative(text, finite=False)


def eps_value(text: str) -> float:
    """State compensation step: finite, >= 0."""
    return _non_negative(text, finite=True)


def window_value(text: str):
    """Observation window in ticks (>= 0), or ``none`` for no window."""
    if text.strip().lower() == "none":
        return None
    return _integer(text, 0, "a non-negative integer or 'none'")


def algorithm_name(text: str) -> str:
    try:
        algorithms.get(text.strip())
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text.strip()


def algorithm_list(text: str) -> list[str]:
    try:
        return algorithms.parse_list(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_command(subparsers, name: str, summary: str, doc: str) -> argparse.ArgumentParser:
    """A subcommand parser whose --help shows the module docstring ``doc``."""
    return subparsers.add_parser(name, help=summary, description=doc.replace("``", ""),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)


def add_scenario_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="quadrants",
                        help="a shipped scenario name or a .toml path (default: quadrants)")
    parser.add_argument("--range", type=range_value, metavar="R", dest="comm_range",
                        help="communication radius of the 'range' topology")
    parser.add_argument("--steps", type=positive_int, metavar="K", help="horizon in ticks (default: the scenario's)")
    parser.add_argument("--agents", type=positive_int, metavar="N",
                        help="agent count of a generated scenario (e.g. random-geometric; default: the scenario's)")


def add_estimator_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--window", type=window_value, default=argparse.SUPPRESS, metavar="W|none",
                        help="observation time window in ticks, or none")
    parser.add_argument("--eps", type=eps_value, default=argparse.SUPPRESS, metavar="E",
                        help="state compensation step epsilon")
    parser.add_argument("--compensation", choices=COMPENSATION_FORMS, default=argparse.SUPPRESS,
                        help="compensation gain form")


def estimator_params(base: Params, args: argparse.Namespace) -> Params:
    """``base`` with the estimator options the user gave."""
    given = {k: getattr(args, k) for k in ("window", "eps", "compensation") if hasattr(args, k)}
    try:
        return replace(base, **given)
    except ValueError as e:
        field, _, msg = str(e).partition(": ")
        raise InputError(field if msg else "params", msg or str(e)) from None
