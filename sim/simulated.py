"""``diskf-mesh up --network simulated``: the whole mesh in this one process.

The world and every agent run their real protocol machines
(``mesh.protocol.world_machine``, ``mesh.protocol.agent_machine``: the encoders, the guard,
the estimators, the rejoin, the run's access rules) on the deterministic
simulated network (``mesh.simulated.simnet``, ``mesh.simulated.simrun``) instead of zenoh: a
virtual clock, and links with a latency and loss model seeded by
``--net-seed`` (default ``--seed``). The run is checked and reported as a
process mesh's is (the engine's replay, the status, the results table and
JSON, the exit status), so a user studies 1,000 agents, or a network slower
than loopback, on a laptop. The time a run takes on the network is virtual:
the line after the run gives it next to the wall time.

    --net-delay-ms MS    one-way delay of every link (default 0.2)
    --net-jitter-ms MS   plus a uniform extra delay in [0, MS) per copy
    --net-loss P         each agent-to-agent message is lost with probability P
                         (the network's loss, outside the run's fault plan:
                         what is lost is not fused, so the run is degraded)
    --net-seed S         the network's seed

The run's own seeded link faults (``--loss``, ``--latency-ms``, ...) apply
in each agent as in a process mesh (the run is then ``as planned``). A run
whose world gives up before its first tick (an agent not there after
``--startup-timeout``) ends ``incomplete`` with the world's reason, exit 3;
with ``--allow-missing`` the world starts without the agents not there, as
a process world does, and they join when they come.
"""
from __future__ import annotations

import argparse
import math
import sys
import time

from diskf_mesh.core.errors import InputError
from diskf_mesh.data.argtypes import fraction, milliseconds, seed_value


NET_DEFAULTS = {"net_delay_ms": 0.2, "net_jitter_ms": 0.0, "net_loss": 0.0, "net_seed": None}


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("simulated network (--network simulated)")
    g.add_argument("--net-delay-ms", type=milliseconds, default=NET_DEFAULTS["net_delay_ms"], metavar="MS",
                   help="one-way delay of every link (default %(default)s)")
    g.add_argument("--net-jitter-ms", type=milliseconds, default=NET_DEFAULTS["net_jitter_ms"], metavar="MS",
                   help="a uniform extra delay in [0, MS) per copy (default %(default)s)")
    g.add_argument("--net-loss", type=fraction, default=NET_DEFAULTS["net_loss"], metavar="P",
                   help="probability that the network loses an agent's message (default %(default)s)")
    g.add_argument("--net-seed", type=seed_value, default=NET_DEFAULTS["net_seed"], metavar="S",
                   help="the simulated network's seed (default: --seed)")


def given(args: argparse.Namespace) -> bool:
    """Whether a --net-* option was given (they need --network simulated)."""
    return any(getattr(args, k) != v for k, v in NET_DEFAULTS.items())


def check_arguments(args: argparse.Namespace) -> None:
    """The options a simulated run refuses (one line, before anything is
    written): those for processes, and a link delay no message could beat
    (``--net-delay-ms`` at or past the agents' ``--collect-timeout``)."""
    for flag, value in (("live", getattr(args, "live", None)), ("profile", args.profile), ("logs", args.logs)):
        if value:
            raise InputError(flag, "is for process meshes, not --network simulated")
    if args.net_delay_ms >= 1000 * args.collect_timeout:
        raise InputError("net-delay-ms", f"{args.net_delay_ms:g} ms is not below --collect-timeout "
                                         f"{args.collect_timeout:g} s: no message could arrive in time to be fused")


def run(args: argparse.Namespace, spec, scn, out) -> tuple:
    """The run (its options checked by ``check_arguments``); prints what
    ``up`` prints but its verdict, ends it as the world process does (``sim.world.finish_run``) and returns the world's
    exit status and the results row (None if the world failed)."""
    from diskf_mesh.data import provenance
    from diskf_mesh.mesh.wire.keys import Keys
    from diskf_mesh.mesh.protocol.log import Log
    from diskf_mesh.mesh.simulated.simnet import Link
    from diskf_mesh.mesh.simulated.simrun import SimPlan, check_size, simulate_run
    from diskf_mesh.studies.experiment import format_table
    from sim.world import failure, finish_run, run_failed, run_timings, setup_run

    K, N = scn.steps, len(scn.agents)
    check_size(scn)
    stages = Stages(K, quiet=args.quiet)
    stages.say(f"{scn.name}: {N} agents + world, {K} ticks, {spec.algorithm}: drawing the scenario's seed {args.seed}")
    run = setup_run(args, spec, scn, provenance.now())
    clock, trace = run.clock, run.trace
    net_seed = args.seed if args.net_seed is None else args.net_seed
    keys = Keys(spec.run_id)
    link = Link(delay=args.net_delay_ms / 1000, jitter=args.net_jitter_ms / 1000, loss=args.net_loss,
                faulty=keys.msgs)
    world_timing, agent_timing = run_timings(args, clock)
    bound = args.startup_timeout + K * (args.tick_timeout + args.collect_timeout) + 60.0
    plan = SimPlan(link, secure=not args.insecure, world_timing=world_timing, agent_timing=agent_timing,
                   allow_missing=args.allow_missing > 0, max_time=bound)
    stages.say(f"start-up: the world and {N} agents join (every agent sees every other's token)")
    t0 = time.monotonic()
    try:
        r = simulate_run(scn, trace, spec.algorithm, args.seed, net_seed=net_seed, plan=plan, faults=run.faults,
                         run_id=spec.run_id, progress=stages.tick, recorder=run.recorder)
    finally:
        stages.close()
    wall = time.monotonic() - t0
    if r.log:
        sys.stderr.write(r.log)
    end = r.outcome.finishes.get("world")
    if end is not None and (error := failure(end, r.record)) is not None:
        return run_failed(error, run, Log("world")), None
    network = {"kind": "simulated", "delay_ms": args.net_delay_ms, "jitter_ms": args.net_jitter_ms,
               "loss": args.net_loss, "lost": r.outcome.lost, "seed": net_seed, "virtual_s": r.outcome.end, "events": r.outcome.events,
               "wall_s": wall, "digest": r.outcome.digest}
    stages.say("checking the run: the engine replays what every agent fused")
    code, results = finish_run(args, run, r.record, r.world.done, out, extra={"network": network},
                               online=getattr(r.world, "online", None))
    rate = K / wall if wall > 0 else math.inf
    print(f"{scn.name}: {N} agents + world on a simulated network (delay {args.net_delay_ms:g} ms, jitter "
          f"{args.net_jitter_ms:g} ms, loss {args.net_loss:g}, network seed {net_seed}), {K} ticks, seed {args.seed}, "
          f"run {spec.run_id}; {r.outcome.end:.3f} s of network time in {wall:.2f} s, {rate:.1f} ticks/s, "
          f"{r.outcome.events} events")
    print(format_table(results))
    row = next(iter(next(iter(results.values())).values()))
    print(f"results: {out}" + (f", estimates: {args.estimates}" if args.estimates else "")
          + (f", recording: {args.record}" if args.record and not row.get("recording_failed") else ""))
    return code, row


class Stages:
    """Where a simulated run is (``cli.progress.Progress``, command ``up``):
    a line per stage (setting up, start-up, the check) and the ticks: on a
    terminal a bar with its ETA, else a line at ticks 1 and K and about
    every tenth of the run with the time to go. ``quiet``: nothing."""

    def __init__(self, K: int, quiet: bool = False):
        from diskf_mesh.cli.progress import Progress

        self.K, self.every = K, max(1, K // 10)
        self.progress = Progress("up", quiet=quiet, total=K, unit="tick")
        self.began = None   # when tick 1 came
        self.shown = 0      # ticks shown so far

    def say(self, line: str) -> None:
        self.progress.note(line)

    def tick(self, k: int) -> None:
        """The world took the reports of tick ``k``."""
        now = time.monotonic()
        if self.began is None:
            self.began = now
        if self.progress.bars or k in (1, self.K) or k % self.every == 0:
            left = (now - self.began) / (k - 1) * (self.K - k) if k > 1 else math.nan
            self.progress.step(f"tick {k}" + (f", about {left:.0f} s to go" if math.isfinite(left) else ""),
                               now - self.began, n=k - self.shown)
            self.shown = k

    def close(self) -> None:
        self.progress.close()
