"""Options and output shared by the subcommands.

Option values are checked by argparse ``type=`` callables
(``diskf_mesh.data.argtypes``). Output paths are checked with ``check_output``
before any work, and written with ``save_json`` (``diskf_mesh.data.outputs``:
atomic, the user's umask, ``-`` for standard output).
"""
from __future__ import annotations

import argparse
from dataclasses import replace

from diskf_mesh.core.errors import InputError
from diskf_mesh.core.model import COMPENSATION_FORMS, Params
from diskf_mesh.data.argtypes import (  # noqa: F401 (re-exported)
    algorithm_list, algorithm_name, eps_value, positive_int, range_value, seed_value, window_value)
from diskf_mesh.data.outputs import (  # noqa: F401 (re-exported)
    check_output, check_output_dir, human_stream, json_safe, save_json)


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
