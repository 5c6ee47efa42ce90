"""``diskf-mesh agent``: one agent of a mesh run, in its own process.

It knows the shared motion model and parameters and only its own sensor
(H, R from the scenario file). Every tick k:

1. wait for the world's tick k (every agent's position, the live set) and for
   its own measurement of tick k (or none);
2. local step (``AgentEstimator.local``), publish ONE message;
3. collect the messages of tick k of its neighbours: the live agents within
   range at tick k (positions from the world). It stops collecting when all
   have arrived, after ``--collect-timeout`` seconds, or as soon as the world
   has opened a later tick;
4. fuse what it has, report the fused estimate to the world.

With ``--rate`` (real time, ``diskf_mesh.mesh.protocol.clock``) step 3 ends at the
deadline instead: ``--deadline-ms`` after tick k reached this agent (default
half the period), or at once for an agent that fell behind; what came later
is a deadline miss, never fused.

The protocol is a state machine (``diskf_mesh.mesh.protocol.agent_machine``: events
in, effects out; its docstring follows one tick through the code); this
module is its shell: zenoh and the wall clock (``diskf_mesh.mesh.process.shell``).
Each step is taken by whichever event makes it possible, in the transport's
callback (zenoh's network thread): the world's tick (its measurement came
just before) runs steps 1-2, the last neighbour's message steps 3-4. The
main thread fires the machine's timers (the collect deadline, the world's
silence) and tells it when the process was not running (SIGSTOP).

Exit status: 0 only when the world says stop with "done" at the run's last
tick; 2 (one line) when another process already holds this agent's id in the
run (``mesh.wire.keys``: every token carries its process's nonce); 3 (one line)
when its estimator diverged: it told the world why and left, and the run goes
on without it (``up`` ends ``incomplete``); 1 with one line on stderr
otherwise: the world stopped the run early, or it has been gone
(its liveliness token) or silent for ``--world-timeout`` seconds. While the
world is gone the agent waits for it (a frozen world comes back).

Link faults (``--loss``, ``--latency-ms``, ... or the scenario's
``[faults]``) act in the receive path on every link into this agent, seeded
by the run's seed (from the world's first tick). An agent started while the
run is in progress (a restart after a crash) joins at the world's next tick
and asks the world for the estimate to start from: a neighbour's fused
estimate of the tick before (``diskf_mesh.mesh.protocol.rejoin``). So does an agent
that was frozen (SIGSTOP) past zenoh's lease and finds, when it wakes, that
the world dropped it: it withdraws its ready token, declares a new one and
rejoins like a restart.

``--profile DIR`` writes where each tick's time went (``mesh.protocol.profile``).
"""
from __future__ import annotations

import argparse
import os
import sys

from diskf_mesh import estimators
from diskf_mesh.data.argtypes import seconds
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process import runspec
from diskf_mesh.mesh.process import zenoh_config
from diskf_mesh.mesh.protocol.agent_machine import AgentMachine, AgentTiming
from diskf_mesh.mesh.wire.keys import Keys, new_nonce
from diskf_mesh.mesh.protocol.log import Log
from diskf_mesh.mesh.process.stopping import exit_on_sigterm
from diskf_mesh.mesh.protocol.profile import AGENT_PHASES, NO_PHASES, Phases
from diskf_mesh.mesh.process.shell import Shell
from diskf_mesh.mesh.process.transport import DuplicateProcess, MeshError, Transport, ZenohTransport
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.data.faults import add_arguments as add_fault_arguments
from diskf_mesh.data.faults import from_args as faults_from_args
from diskf_mesh.data.scenario import Scenario

__all__ = ["Agent", "AgentTiming", "register", "run"]


class Agent:
    """An ``AgentMachine`` run by a ``Shell`` over ``transport``: ``run``
    returns the number of ticks worked on, or raises ``MeshError``
    (``DuplicateProcess``: exit status 2) with the machine's reason."""

    def __init__(self, scn: Scenario, agent_id: int, algorithm: str, keys: Keys, transport: Transport,
                 timing: AgentTiming = AgentTiming(), log: Log | None = None,
                 faults: FaultConfig | FaultModel | None = None, profile: Phases = NO_PHASES):
        try:
            self.machine = AgentMachine(scn, agent_id, estimators.get(algorithm), keys, new_nonce(), timing, faults,
                                        log, profile)
        except ValueError as e:
            raise MeshError(str(e)) from None
        self.shell = Shell(self.machine, transport, profile)

    def run(self) -> int:
        fin = self.shell.run()
        if fin.code == DuplicateProcess.status:
            raise DuplicateProcess(fin.reason)
        if fin.code:
            err = MeshError(fin.reason)
            err.status = fin.code
            raise err
        return self.machine.ticks_worked


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def register(subparsers) -> None:
    p = subparsers.add_parser("agent", help="one agent process of a mesh run",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--id", type=int, required=True, dest="agent_id", help="this agent's id in the scenario")
    runspec.add_arguments(p)
    p.add_argument("--collect-timeout", type=seconds, default=AgentTiming.collect_timeout, metavar="S",
                   help="seconds to wait for the neighbours' messages of a tick (default %(default)s)")
    p.add_argument("--world-timeout", type=seconds, default=AgentTiming.world_timeout, metavar="S",
                   help="seconds of silence from the world before giving up (default %(default)s)")
    p.add_argument("--profile", metavar="DIR",
                   help="measure where each tick's time goes (decode, guard, local, fuse, encode, publish, "
                        "wait) and write DIR/agent-<id>.json at exit")
    realtime.add_arguments(p, world=False)
    add_fault_arguments(p)
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def batch_scheduling() -> None:
    """Put this process (its threads to come: call it before zenoh starts
    them) under Linux's SCHED_BATCH: a woken agent thread then does not
    preempt the thread running on its core, e.g. the world's sender halfway
    through opening a tick for every agent. On two cores shared by ten
    processes this measured ~10-20 % more ticks per second and fewer context
    switches; the world keeps the normal policy. Elsewhere, a no-op."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):
        pass


def run(args: argparse.Namespace) -> int:
    exit_on_sigterm()  # first thing: stopped at any moment, its session closed (mesh.process.stopping)
    spec = runspec.from_args(args)
    scn = spec.load()
    clock = realtime.from_args(args)
    log = Log(f"agent {args.agent_id}")
    if clock is None:  # real time wants the deadline's wake-up at once, not after the running thread's slice
        batch_scheduling()
    zenoh = zenoh_config.from_args(args, credentials.agent_identity(args.agent_id), spec.run_id)
    prof = Phases(AGENT_PHASES, f"agent {args.agent_id}") if args.profile else NO_PHASES
    try:
        with ZenohTransport(zenoh) as transport:
            agent = Agent(scn, args.agent_id, spec.algorithm, Keys(spec.run_id), transport,
                          AgentTiming(args.collect_timeout, args.world_timeout, clock), log,
                          faults_from_args(args, scn.faults), prof)
            agent.run()
    except MeshError as e:
        log.error(str(e))
        return e.status
    finally:
        if prof:
            prof.write(args.profile, f"agent-{args.agent_id}")
    return 0


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("agent", __spec__.name))
