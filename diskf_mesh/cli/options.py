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
from diskf_mesh.data.argtypes import (  # noqa: F401 (re-exported)
    add_ticks, estimator_list, estimator_name, fraction, milliseconds, positive, positive_int, range_value, seed_value,
    setting_value)
from diskf_mesh.estimators import DEFAULT, NAMES, SETTINGS, Params
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
    add_ticks(parser)
    parser.add_argument("--agents", type=positive_int, metavar="N",
                        help="agent count of a generated scenario (e.g. random-geometric; default: the scenario's)")


def add_estimator_choice(parser, many: bool = False) -> None:
    """``--estimator NAME``, or with ``many`` ``--estimators all|A[,A...]``;
    each command takes either spelling (and ``--algorithm(s)``, the old one)."""
    if many:
        parser.add_argument("--estimators", "--estimator", "--algorithms", "--algorithm", dest="estimators", type=estimator_list, default="all",
                            metavar="all|E[,E...]", help=f"'all' or a comma list of {', '.join(NAMES)}")
    else:
        parser.add_argument("--estimator", "--estimators", "--algorithm", dest="estimator", type=estimator_name, default=DEFAULT,
                            help=f"one of {', '.join(NAMES)} (default {DEFAULT})")


def add_estimator_options(parser: argparse.ArgumentParser) -> None:
    """One option per scalar setting the registered estimators declare
    (``estimators.SETTINGS``): ``--window``, ``--eps``, ... Absent options
    keep the scenario's (or trace's) value."""
    g = parser.add_argument_group("estimator settings (default: the scenario's [estimator] table)")
    for s in SETTINGS.values():
        if s.table:
            continue  # a sub-table of switches: the scenario's [estimator.<name>]
        if s.choices:
            g.add_argument(s.flag, choices=s.choices, default=argparse.SUPPRESS, help=s.doc)
        else:
            meta = {bool: "on|off", int: "N", float: "X", str: "TEXT"}.get(s.type, "V") + ("|none" if s.optional else "")
            g.add_argument(s.flag, type=setting_value(s), default=argparse.SUPPRESS, metavar=meta,
                           help=f"{s.doc} (default {s.default!r})".replace("%", "%%"))


def estimator_params(base: Params, args: argparse.Namespace) -> Params:
    """``base`` with the estimator options the user gave."""
    given = {s.name: getattr(args, s.name) for s in SETTINGS.values() if hasattr(args, s.name)}
    try:
        return replace(base, **given)
    except ValueError as e:
        field, _, msg = str(e).partition(": ")
        raise InputError(field if msg else "params", msg or str(e)) from None
