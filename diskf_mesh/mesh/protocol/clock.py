"""Real-time mode: the world's wall clock and every agent's deadline.

Without ``--rate`` a run is the lockstep (``sim.world``): tick k+1 opens
when every live agent has reported tick k, and an agent fuses once every
neighbour's message of the tick is in (or ``--collect-timeout``). That is
bit for bit the engine.

With ``--rate HZ`` (``up``, ``world`` and ``agent``) the run follows the
wall clock and nothing waits for a slow process:

    world   opens tick k at t0 + (k - 1) / HZ (t0: when tick 1 opens),
            whether or not the reports of tick k - 1 came in. Tick k ends
            when tick k + 1 opens (the last tick one period after it
            opened): a live agent whose report of tick k is not in by then
            counts one report deadline miss. Its report is still taken when
            it comes later (the estimate is real, and needed to replay the
            run), counted ``late_reports``; after the last tick's end the
            world waits at most ``--tick-timeout`` for those, then stops.
    agent   runs its local step as soon as tick k and its measurement are
            in, publishes, and fuses what arrived by its deadline: the
            moment tick k reached it + ``deadline_s``
            (``--deadline-ms``, default ``DEADLINE_FRACTION`` of the
            period), or sooner if every neighbour's message is in. A
            neighbour's message not in by then is a message deadline miss
            (the report's verdict "late"); a copy arriving later is counted
            late by the inbox and never fused. An agent that fell behind
            (its deadline passed before it got to the tick) fuses at once
            what is there: it catches up instead of waiting.

So link latency beyond the deadline (``--latency-ms``) becomes misses,
never waits. Every fused set is in the agent's report (``wire.Report.fused``)
and so in the estimates document (``fused``) and the recording: ``diskf-mesh
replay RUN.mcap`` re-runs the engine on exactly those sets and reproduces
every estimate bit for bit, however the timing fell.

The result JSON gains ``deadline_misses`` (per agent and in total: messages
not fused in time, reports not in at the tick's end, and the miss rate over
both) and ``tick_period`` (target, mean, p99 of the jitter |period - 1/HZ|).
Misses are what a real-time run measures; a run that could not keep up
says so in its exit status: more than ``--max-miss-rate`` of its messages
and reports missed (default ``MAX_MISS_RATE``, 5 %) exits
``TOO_MANY_MISSES`` with one line, fewer give a warning line and exit 0
(``--max-miss-rate 1`` accepts any; a rate sweep does). Reports that never
came at all are missing agent-ticks as in lockstep (exit 3,
``--allow-missing``).

Real time needs a wider window than lockstep's one tick ahead: an agent
takes the world's ticks and its neighbours' messages up to ``LEAD_TICKS``
ahead of the tick it works on.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from diskf_mesh.core import exits
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.argtypes import fraction, positive

DEADLINE_FRACTION = 0.5  # default agent deadline: this share of the period after tick k reached it
LEAD_TICKS = 64          # how far ahead of its tick an agent takes the world's ticks and neighbours' messages
TOO_MANY_MISSES = exits.TOO_MANY_MISSES  # exit status of a real-time run whose miss rate exceeds --max-miss-rate
MAX_MISS_RATE = 0.05     # ... by default: a run that missed more than this share did not keep up


@dataclass(frozen=True)
class Clock:
    """A real-time run's rate and the agents' deadline (seconds after tick
    k reached an agent)."""

    rate_hz: float
    deadline_s: float

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    def to_argv(self) -> list:
        return ["--rate", repr(float(self.rate_hz)), "--deadline-ms", repr(1000.0 * self.deadline_s)]


def add_arguments(parser: argparse.ArgumentParser, world: bool = True) -> None:
    """``--rate``, ``--deadline-ms`` and (``world``) ``--max-miss-rate``."""
    g = parser.add_argument_group("real time (diskf_mesh.mesh.protocol.clock; default: lockstep)")
    g.add_argument("--rate", type=positive, metavar="HZ",
                   help="run on the wall clock: tick k opens at k/HZ s whether or not the reports came in")
    g.add_argument("--deadline-ms", type=positive, metavar="MS",
                   help="with --rate: an agent fuses what arrived this long after tick k reached it "
                        f"(default {DEADLINE_FRACTION:g} of the period)")
    if world:
        g.add_argument("--max-miss-rate", type=fraction, metavar="FRACTION",
                       help=f"with --rate: exit {TOO_MANY_MISSES} if more than this share of messages and "
                            f"reports missed their deadline (default {MAX_MISS_RATE:g}; 1 accepts any)")


def from_args(args: argparse.Namespace) -> Clock | None:
    """The run's clock, or None (lockstep). ``InputError`` for a deadline
    without a rate, or one not shorter than the period (the report would
    always be late)."""
    rate, deadline_ms = getattr(args, "rate", None), getattr(args, "deadline_ms", None)
    if rate is None:
        if deadline_ms is not None:
            raise InputError("deadline-ms", "needs --rate (lockstep has --collect-timeout)")
        if getattr(args, "max_miss_rate", None) is not None:
            raise InputError("max-miss-rate", "needs --rate (lockstep has no deadlines)")
        return None
    period = 1.0 / rate
    deadline = DEADLINE_FRACTION * period if deadline_ms is None else deadline_ms / 1000.0
    if deadline >= period:
        raise InputError("deadline-ms", f"must be shorter than the period ({1000.0 * period:g} ms at {rate:g} Hz), "
                                        f"got {deadline_ms:g}")
    return Clock(rate, deadline)


def max_miss_rate(args: argparse.Namespace) -> float:
    """The run's ``--max-miss-rate``, or ``MAX_MISS_RATE``."""
    given = getattr(args, "max_miss_rate", None)
    return MAX_MISS_RATE if given is None else given


def argv(args: argparse.Namespace) -> tuple:
    """(world's, agents') flags of ``up``'s real-time options."""
    clock = from_args(args)
    if clock is None:
        return [], []
    world = clock.to_argv()
    if args.max_miss_rate is not None:
        world += ["--max-miss-rate", repr(args.max_miss_rate)]
    return world, clock.to_argv()


def period_stats(opened_at, clock: Clock) -> dict:
    """The actual tick period from the monotonic times the ticks opened:
    target, mean, and the p99 and max of the jitter |period - 1/HZ| (s)."""
    t = np.asarray(opened_at, dtype=float)
    periods = np.diff(t)
    out = {"target_s": clock.period_s, "ticks": int(t.size)}
    if periods.size:
        jitter = np.abs(periods - clock.period_s)
        out.update(mean_s=float(periods.mean()), p99_jitter_s=float(np.percentile(jitter, 99)),
                   max_jitter_s=float(jitter.max()))
    return out


def agents_deadline(clock: Clock | None, collect_s: float) -> float:
    """How long after a tick reaches an agent a neighbour's copy may still
    be fused: real time's deadline, else the lockstep collect timeout (a
    copy the link faults delay past it is not planned to be fused)."""
    return collect_s if clock is None else clock.deadline_s
