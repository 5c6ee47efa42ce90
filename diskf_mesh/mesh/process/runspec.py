"""What every process of one mesh run must agree on, and the command lines
that start them.

``RunSpec`` holds the scenario (shipped name or path, with the same
``--topology``/``--range``/``--agents`` overrides as the engine), the
algorithm and the run id. ``world_command``, ``agent_command``,
``router_command`` and ``host_command`` are the one place a process's command
line is built: the launcher (``up``, ``up --hosts``, ``host``), the
benchmarks and the compose files (checked by tests) all use them.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

from diskf_mesh import estimators
from diskf_mesh.core.errors import InputError
from diskf_mesh.data import lies as lying
from diskf_mesh.data.argtypes import estimator_name, positive_int, range_value
from diskf_mesh.data.scenario import TOPOLOGIES, Scenario, load_scenario
from diskf_mesh.mesh.wire.keys import check_run_id
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions

DEFAULT_RUN_ID = "default"
WORLD_MODULE = "sim.world"
AGENT_MODULE = "agents.agent"
ROUTER_MODULE = "sim.router"
HOST_MODULE = "sim.host"
HOST_COUNT_FLAG = "--agent-count"  # ``host``'s --agents is its range of ids: the generated count is this


@dataclass(frozen=True)
class RunSpec:
    scenario: str = "dynamic"
    algorithm: str = estimators.DEFAULT
    run_id: str = DEFAULT_RUN_ID
    topology: str | None = None
    comm_range: float | None = None
    agents: int | None = None  # agent count of a generated scenario
    lies: tuple | None = None  # ``data.lies.Lie``s given with --lie (None: the scenario's [[faults.lies]])

    def load(self, ticks: int | None = None) -> Scenario:
        """The scenario with the overrides applied (``InputError`` if bad)."""
        check_run_id(self.run_id)
        scn = load_scenario(self.scenario, agents=self.agents)
        if self.lies is not None:
            scn = scn.with_lies(self.lies)
        return scn.with_overrides(topology=self.topology, comm_range=self.comm_range, steps=ticks)

    def to_argv(self, count_flag: str = "--agents") -> list:
        out = ["--scenario", self.scenario, "--algorithm", self.algorithm, "--run-id", self.run_id]
        if self.topology is not None:
            out += ["--topology", self.topology]
        if self.comm_range is not None:
            out += ["--range", repr(float(self.comm_range))]
        if self.agents is not None:
            out += [count_flag, str(self.agents)]
        if self.lies is not None:
            out += lying.to_argv(self.lies)
        return out


def setting_label(scn: Scenario) -> str:
    """The column label of a result, as ``experiment`` names its settings."""
    return f"range={scn.comm_range:g}" if scn.topology == "range" else scn.topology


def add_arguments(parser: argparse.ArgumentParser, run_id_default: str | None = DEFAULT_RUN_ID,
                  count_flag: str = "--agents") -> None:
    g = parser.add_argument_group("run")
    g.add_argument("--scenario", default="dynamic", help="a shipped scenario name or a .toml path (default: dynamic)")
    g.add_argument("--estimator", "--estimators", "--algorithm", dest="algorithm", type=estimator_name,
                   default=estimators.DEFAULT,
                   help=f"one of {', '.join(estimators.NAMES)} (default: {estimators.DEFAULT})")
    g.add_argument("--run-id", default=run_id_default,
                   help="key prefix diskf/<run-id>/ shared by the world and its agents"
                        + (f" (default: {run_id_default})" if run_id_default else " (default: a fresh one)"))
    g.add_argument("--topology", choices=TOPOLOGIES, help="override the scenario's topology")
    g.add_argument("--range", type=range_value, dest="comm_range", metavar="R",
                   help="communication radius (implies --topology range)")
    g.add_argument(count_flag, type=positive_int, dest="agents", metavar="N", help="agent count of a generated scenario")
    lying.add_arguments(g)


def from_args(args: argparse.Namespace, run_id: str | None = None) -> RunSpec:
    return RunSpec(scenario=args.scenario, algorithm=args.algorithm, run_id=run_id or args.run_id,
                   topology=args.topology, comm_range=args.comm_range, agents=args.agents,
                   lies=None if getattr(args, "lie", None) is None else tuple(args.lie))


def world_command(spec: RunSpec, ticks: int, seed: int, zenoh: ZenohOptions, extra=(),
                  python: str | None = None) -> list:
    """argv of the world process."""
    return [python or sys.executable, "-m", WORLD_MODULE, *spec.to_argv(), "--ticks", str(ticks),
            "--seed", str(seed), *zenoh.to_argv(), *extra]


def agent_command(spec: RunSpec, agent_id: int, zenoh: ZenohOptions, extra=(), python: str | None = None) -> list:
    """argv of agent ``agent_id``."""
    return [python or sys.executable, "-m", AGENT_MODULE, "--id", str(agent_id), *spec.to_argv(),
            *zenoh.to_argv(), *extra]


def router_command(run_id: str | None, zenoh: ZenohOptions, python: str | None = None) -> list:
    """argv of a zenoh router of run ``run_id`` (``diskf-mesh router``)."""
    return [python or sys.executable, "-m", ROUTER_MODULE, *(["--run-id", run_id] if run_id else []),
            *zenoh.to_argv()]


def host_command(spec: RunSpec, ids, zenoh: ZenohOptions, extra=(), python: str | None = None) -> list:
    """argv of the shard of agents ``ids`` on one host (``diskf-mesh host``)."""
    return [python or sys.executable, "-m", HOST_MODULE, "--agents", id_ranges(ids), *spec.to_argv(HOST_COUNT_FLAG),
            *zenoh.to_argv(), *extra]


def id_ranges(ids) -> str:
    """Agent ids as ``host --agents`` takes them: ``1-25,30``."""
    ids, parts = sorted(set(int(i) for i in ids)), []
    for i in ids:
        if parts and parts[-1][1] == i - 1:
            parts[-1][1] = i
        else:
            parts.append([i, i])
    return ",".join(f"{a}" if a == b else f"{a}-{b}" for a, b in parts)


def parse_ids(text: str) -> tuple:
    """``1-25``, ``1,3,7-9``: agent ids in increasing order (``InputError``
    on a bad item, an empty or reversed range, or an id given twice)."""
    out = []
    for item in str(text).split(","):
        a, sep, b = item.strip().partition("-")
        try:
            lo, hi = int(a), int(b) if sep else int(a)
        except ValueError:
            raise InputError("agents", f"expected ids and ranges like 1-25,30, got {text!r}") from None
        if lo < 0 or hi < lo:
            raise InputError("agents", f"bad range {item.strip()!r} in {text!r} (ids >= 0, low-high)")
        out += range(lo, hi + 1)
    if len(set(out)) != len(out):
        raise InputError("agents", f"an id is given twice in {text!r}")
    return tuple(sorted(out))
