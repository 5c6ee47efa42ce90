"""The world's check as the run goes, alone: CPU per tick of ``OnlineCheck.tick``
replaying a simulated run's record, hot (the ticks back to back in one thread)
and woken (``CheckThread``: each tick handed to the check's thread, its
finding taken after a pause, as the agents' work makes in the mesh).

    python benchmarks/check_bench.py [--agents 9,25] [--ticks 200] [--algorithm diskf]
                                     [--repeat 3] [--gap-ms 3]

For each agent count: one run of the random-geometric scenario on the
simulated network (seed 0), whose world record is then checked again and
again. Columns (ms of CPU per tick, the best of ``--repeat``):

    hot        ``OnlineCheck.tick`` on every tick in turn, one thread
    woken      the check's thread, each tick handed over and its finding
               taken ``--gap-ms`` later (the process's CPU per tick: the
               thread's replay and the caller's side)
    hand-off   the caller's side of it: ``submit`` and ``result``

CPU time, not wall time, so the figures hold on a machine other work
shares better than rates do; compare two trees with ``benchmarks/versus.py``.
"""
from __future__ import annotations

import argparse
import sys
import time

from diskf_mesh import estimators
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.mesh.process.checker import CheckThread
from diskf_mesh.mesh.protocol.run_status import OnlineCheck
from diskf_mesh.mesh.simulated.simrun import SimPlan, simulate_run

RUN = "bench"


def recorded(agents: int, ticks: int, algorithm: str):
    """(scenario, trace, world record) of one simulated run."""
    scn = load_scenario("random-geometric", agents=agents).with_overrides(steps=ticks)
    trace = simulate(scn, [0])
    r = simulate_run(scn, trace, algorithm, 0, run_id=RUN, plan=SimPlan(online=False))
    if r.status.status != "exact":
        raise SystemExit(f"the simulated run is {r.status.status}: {r.status.reason}")
    return scn, trace, r.record


def hot(make, rec, K: int) -> float:
    """CPU ms per tick of ``OnlineCheck.tick`` on ticks 1..K back to back."""
    check = make()
    t0 = time.process_time()
    for k in range(1, K + 1):
        if check.tick(rec, k):
            raise SystemExit(f"the check named a liar in an exact run at tick {k}")
    return 1e3 * (time.process_time() - t0) / K


def woken(make, rec, K: int, gap_s: float) -> tuple:
    """(the process's CPU ms per tick, the caller's): each tick handed over,
    then its finding taken ``gap_s`` later (as the world hands a tick over
    when the next one opens and takes the finding before the one after)."""
    check = CheckThread(make)
    spent = 0.0
    try:
        check.result(rec, 1)  # the check made, its first tick done: from here on, the ticks
        p0 = time.process_time()
        for k in range(2, K + 1):
            t0 = time.process_time()
            check.submit(rec, k)
            spent += time.process_time() - t0
            time.sleep(gap_s)
            t0 = time.process_time()
            found = check.result(rec, k)
            spent += time.process_time() - t0
            if found:
                raise SystemExit(f"the check named a liar in an exact run at tick {k}")
        return 1e3 * (time.process_time() - p0) / (K - 1), 1e3 * spent / (K - 1)
    finally:
        check.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agents", default="9,25")
    p.add_argument("--ticks", type=int, default=200)
    p.add_argument("--algorithm", default="diskf")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--gap-ms", type=float, default=3.0)
    args = p.parse_args(argv)
    print(f"OnlineCheck.tick, {args.algorithm}, random-geometric, {args.ticks} ticks, CPU ms per tick, "
          f"best of {args.repeat}\n")
    print("| agents | hot | woken | hand-off |")
    print("|---:|---:|---:|---:|")
    for n in (int(a) for a in args.agents.split(",")):
        scn, trace, rec = recorded(n, args.ticks, args.algorithm)
        make = lambda: OnlineCheck(trace, estimators.get(args.algorithm), scn.params,  # noqa: E731
                                   run_id=RUN, seed=0)
        K = rec.reported.shape[0]
        h = min(hot(make, rec, K) for _ in range(args.repeat))
        w = [woken(make, rec, K, args.gap_ms / 1e3) for _ in range(args.repeat)]
        print(f"| {n} | {h:.3f} | {min(c for c, _ in w):.3f} | {min(s for _, s in w):.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
