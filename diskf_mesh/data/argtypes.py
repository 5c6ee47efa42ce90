"""Command-line value types, shared by the commands and the mesh processes.

Option values are checked by argparse ``type=`` callables, so a bad value
ends as argparse's one line ``error: argument --X: ...`` with status 2
before any work is done.
"""
from __future__ import annotations

import argparse
import math
import sys

from diskf_mesh import estimators

MAX_S = 86_400.0           # a day: no duration option (a timeout, a delay) may be longer
MAX_MS = 1000.0 * MAX_S


class Renamed(argparse._StoreAction):
    """The old spelling of an option, kept working and out of ``--help``:
    it stores into the new option's ``dest`` and says so in one line on
    standard error, ``note: --steps is now --ticks``."""

    def __init__(self, option_strings, dest, now: str = "", **kw):
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kw)
        self.now = now

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"note: {option_string} is now {self.now}", file=sys.stderr)
        super().__call__(parser, namespace, values, option_string)


def add_ticks(parser, help: str = "horizon in ticks (default: the scenario's)", **kw) -> None:
    """``--ticks K`` (``--steps`` the old spelling), into ``ticks``."""
    kind = kw.pop("type", positive_int)
    parser.add_argument("--ticks", dest="ticks", metavar="K", type=kind, help=help, **kw)
    parser.add_argument("--steps", dest="ticks", metavar="K", type=kind, action=Renamed, now="--ticks",
                        default=argparse.SUPPRESS)


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


def _number(text: str, ok, what: str) -> float:
    """``float(text)`` if ``ok`` of it holds (NaN never does), else argparse's
    error "must be <what>"."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not ok(v):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return v


def fraction(text: str) -> float:
    """A number in [0, 1]: a probability (``--loss``), a share (``--allow-missing``,
    ``--max-miss-rate``)."""
    return _number(text, lambda v: 0.0 <= v <= 1.0, "a number between 0 and 1")


def milliseconds(text: str) -> float:
    """A non-negative number of milliseconds up to a day (``--latency-ms``, ``--net-delay-ms``)."""
    return _number(text, lambda v: 0 <= v <= MAX_MS, f"a number of milliseconds from 0 to {MAX_MS:.0f} (a day)")


def seconds(text: str) -> float:
    """A number of seconds > 0, up to a day (``--tick-timeout``)."""
    return _number(text, lambda v: 0 < v <= MAX_S, f"a number of seconds above 0, up to {MAX_S:.0f} (a day)")


def positive(text: str) -> float:
    """A finite number > 0 (``--rate``, ``--deadline-ms``)."""
    return _number(text, lambda v: math.isfinite(v) and v > 0, "a positive number")


def setting_value(setting):
    """The argparse type of an estimator ``Setting`` (``Setting.from_text``)."""
    def parse(text: str):
        try:
            return setting.from_text(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    parse.__name__ = setting.name  # argparse names the type in "invalid <name> value"
    return parse


def estimator_name(text: str) -> str:
    if "," in text:
        raise argparse.ArgumentTypeError(f"one estimator here, got {text.strip()!r} (experiment compares several)")
    try:
        estimators.get(text.strip())
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text.strip()


def estimator_list(text: str) -> list[str]:
    try:
        return estimators.parse_list(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
