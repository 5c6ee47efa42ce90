"""One agent's work per tick, without zenoh: what an agent process spends in
Python (protocol and math) when its callbacks are fed recorded payloads in
one thread. Prints figures; not a test.

    python benchmarks/agent_bench.py [--scenario dynamic] [--agents N] [--algorithm diskf]
                                     [--ticks 200] [--agent ID] [--repeat 5]

The payloads of every tick are made first, from the scenario's trace and the
other agents' messages (``mesh.protocol.estimator.lockstep``): the world's tick and
this agent's measurement, then its in-range neighbours' messages on their
addressed keys. Then they reach the agent's machine (``mesh.protocol.agent_machine``)
the way zenoh's callbacks hand them over in a real run: through its shell
(``mesh.process.shell.Shell``: the lock, the event, ``handle``, the effects carried
out) over a transport whose puts go nowhere: decode, guard, local step,
encode, fusion, report. The table splits the time
into the estimator's two calls (math) and the rest (protocol); the best of
``--repeat`` rounds is kept (the machine is shared). In a mesh run the same
work costs about twice this, since ten processes share two cores and their
caches (``mesh_bench.py --profile``).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from diskf_mesh import estimators as algorithms
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.argtypes import positive_int
from diskf_mesh.data.scenario import simulate
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.protocol.agent_machine import AgentMachine
from diskf_mesh.mesh.protocol.estimator import AgentEstimator, lockstep, neighbours
from diskf_mesh.mesh.protocol.events import AskTokens, Token, Tokens
from diskf_mesh.mesh.wire.keys import Keys, key_matches
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.shell import Shell

RUN = "bench"


def recorded_ticks(spec: RunSpec, ticks: int, me: int) -> list:
    """Per tick, [(key, payload)] as agent ``me`` receives them."""
    scn = spec.load(ticks)
    trace = simulate(scn, [0])
    ids = [a.id for a in scn.agents]
    keys = Keys(RUN)
    j = ids.index(me)
    p = int(scn.sensors().p[j])
    exchanged = algorithms.get(spec.algorithm).exchanged  # what its messages carry
    out = []
    for k, msgs, _ in lockstep(scn, spec.algorithm, trace):
        pos = trace.positions[k - 1]
        tick = wire.Tick(RUN, k, ticks, 0, spec.algorithm, scn.topology, scn.comm_range, pos, tuple(ids))
        samples = [(keys.meas(me), wire.encode_measurement(RUN, k, me, bool(trace.has[0, k - 1, j]),
                                                            trace.y[0, k - 1, j, :p])),
                   (keys.tick, wire.encode_tick(tick))]
        samples += [(keys.msg(o, to=[me]), wire.encode(RUN, o, k, msgs[o], exchanged))
                    for o in neighbours(scn, me, pos) if o != me]
        out.append(samples)
    return out


class Sink:
    """A transport whose puts go nowhere; it keeps the shell's subscriptions
    so that a recorded sample reaches the callback zenoh would call."""

    def __init__(self):
        self.subscriptions = []  # (key expression, callback)

    def put(self, key, payload, express=True):
        pass

    def subscribe(self, key_expr, on_sample):
        self.subscriptions.append((key_expr, on_sample))

    def watch_tokens(self, key_expr, on_change):
        pass

    def callback(self, key: str):
        """The callback of the one subscription matching ``key``."""
        cb, = [cb for expr, cb in self.subscriptions if key_matches(expr, key)]
        return cb


def one_round(spec: RunSpec, me: int, feed: list) -> dict:
    """Seconds in all of the shell's sample callbacks and in the estimator's two calls."""
    scn = spec.load(len(feed))
    keys = Keys(RUN)
    agent = AgentMachine(scn, me, algorithms.get(spec.algorithm), keys, "bench")
    sink = Sink()
    Shell(agent, sink, clock=lambda: 0.0).start()  # its subscriptions; the main loop is not needed
    ask, = [e for e in agent.handle(Token(keys.world("w"), True), 0.0) if isinstance(e, AskTokens)]
    agent.handle(Tokens(ask.qid, ()), 0.0)
    for i in (a.id for a in scn.agents):
        agent.handle(Token(keys.alive(i, "bench" if i == me else "w"), True), 0.0)
    calls = {key: sink.callback(key) for samples in feed for key, _ in samples}
    math_s = [0.0]
    total = 0.0
    for samples in feed:
        for key, payload in samples:
            joined = agent.est is not None
            cb = calls[key]
            t0 = time.perf_counter()
            cb(key, payload)
            total += time.perf_counter() - t0
            if not joined and agent.est is not None:
                timed(agent.est, math_s)  # made on tick 1: its local step is not in the math
    if agent.k != len(feed) + 1:
        raise RuntimeError(f"the agent stopped at tick {agent.k}")
    if agent.counters.rejected:  # a feed the agent refuses measures another path than a run's
        raise RuntimeError(f"the agent rejected recorded messages: {dict(agent.counters.rejected)}")
    return {"total": total, "math": math_s[0]}


def timed(est: AgentEstimator, acc: list) -> None:
    """Add the time of ``est.local`` and ``est.fuse`` to ``acc[0]``."""
    for name in ("local", "fuse"):
        f = getattr(est, name)

        def wrapper(*a, _f=f, **kw):
            t0 = time.perf_counter()
            try:
                return _f(*a, **kw)
            finally:
                acc[0] += time.perf_counter() - t0

        setattr(est, name, wrapper)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default="dynamic")
    p.add_argument("--agents", type=positive_int, help="agent count of a generated scenario (e.g. random-geometric)")
    p.add_argument("--algorithm", default="diskf", choices=algorithms.NAMES)
    p.add_argument("--ticks", type=int, default=200)
    p.add_argument("--agent", type=int, help="the agent's id (default: the scenario's fifth, or its last)")
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args(argv)
    spec = RunSpec(args.scenario, args.algorithm, agents=args.agents)
    try:
        ids = [a.id for a in spec.load(args.ticks).agents]
    except InputError as e:
        p.error(str(e))
    me = args.agent if args.agent is not None else ids[min(4, len(ids) - 1)]
    if me not in ids:
        p.error(f"agent {me} is not in {args.scenario} (ids {', '.join(map(str, ids))})")
    feed = recorded_ticks(spec, args.ticks, me)
    best = min((one_round(spec, me, feed) for _ in range(max(args.repeat, 1))), key=lambda r: r["total"])
    us = {k: 1e6 * v / args.ticks for k, v in best.items()}
    heard = np.mean([len(s) - 2 for s in feed])
    print(f"\n{args.algorithm} on {args.scenario} ({len(ids)} agents), agent {me}, {args.ticks} ticks, "
          f"{heard:.1f} neighbour messages a tick; best of {args.repeat} rounds, one thread, no zenoh\n")
    print("| µs per tick | all of the callbacks | math (local + fuse) | protocol (the rest) |")
    print("|---|---:|---:|---:|")
    print(f"| {args.algorithm} | {us['total']:.0f} | {us['math']:.0f} | {us['total'] - us['math']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
