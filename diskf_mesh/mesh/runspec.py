"""What every process of one mesh run must agree on, and the command lines
that start them.

``RunSpec`` holds the scenario (shipped name or path, with the same
``--topology``/``--range``/``--agents`` overrides as the engine), the
algorithm and the run id. ``world_command`` and ``agent_command`` are the one
place a process's command line is built: the launcher (``up``), the
benchmark and ``docker-compose.yml`` (checked by a test) all use them.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

from diskf_mesh import estimators
from diskf_mesh.data.argtypes import estimator_name, positive_int, range_value
from diskf_mesh.data.scenario import TOPOLOGIES, Scenario, load_scenario
from diskf_mesh.mesh.keys import check_run_id
from diskf_mesh.mesh.zenoh_config import ZenohOptions

DEFAULT_RUN_ID = "default"
WORLD_MODULE = "sim.world"
AGENT_MODULE = "agents.agent"


@dataclass(frozen=True)
class RunSpec:
    scenario: str = "dynamic"
    algorithm: str = "diskf"
    run_id: str = DEFAULT_RUN_ID
    topology: str | None = None
    comm_range: float | None = None
    agents: int | None = None  # agent count of a generated scenario

    def load(self, ticks: int | None = None) -> Scenario:
        """The scenario with the overrides applied (``InputError`` if bad)."""
        check_run_id(self.run_id)
        scn = load_scenario(self.scenario, agents=self.agents)
        return scn.with_overrides(topology=self.topology, comm_range=self.comm_range, steps=ticks)

    def to_argv(self) -> list:
        out = ["--scenario", self.scenario, "--algorithm", self.algorithm, "--run-id", self.run_id]
        if self.topology is not None:
            out += ["--topology", self.topology]
        if self.comm_range is not None:
            out += ["--range", repr(float(self.comm_range))]
        if self.agents is not None:
            out += ["--agents", str(self.agents)]
        return out


def setting_label(scn: Scenario) -> str:
    """The column label of a result, as ``experiment`` names its settings."""
    return f"range={scn.comm_range:g}" if scn.topology == "range" else scn.topology


def add_arguments(parser: argparse.ArgumentParser, run_id_default: str | None = DEFAULT_RUN_ID) -> None:
    g = parser.add_argument_group("run")
    g.add_argument("--scenario", default="dynamic", help="a shipped scenario name or a .toml path (default: dynamic)")
    g.add_argument("--estimator", "--algorithm", dest="algorithm", type=estimator_name, default="diskf",
                   help=f"one of {', '.join(estimators.NAMES)} (default: diskf)")
    g.add_argument("--run-id", default=run_id_default,
                   help="key prefix diskf/<run-id>/ shared by the world and its agents"
                        + (f" (default: {run_id_default})" if run_id_default else " (default: a fresh one)"))
    g.add_argument("--topology", choices=TOPOLOGIES, help="override the scenario's topology")
    g.add_argument("--range", type=range_value, dest="comm_range", metavar="R",
                   help="communication radius (implies --topology range)")
    g.add_argument("--agents", type=positive_int, metavar="N", help="agent count of a generated scenario")


def from_args(args: argparse.Namespace, run_id: str | None = None) -> RunSpec:
    return RunSpec(scenario=args.scenario, algorithm=args.algorithm, run_id=run_id or args.run_id,
                   topology=args.topology, comm_range=args.comm_range, agents=args.agents)


def world_command(spec: RunSpec, ticks: int, seed: int, zenoh: ZenohOptions, extra=(),
                  python: str | None = None) -> list:
    """argv of the world process."""
    return [python or sys.executable, "-m", WORLD_MODULE, *spec.to_argv(), "--ticks", str(ticks),
            "--seed", str(seed), *zenoh.to_argv(), *extra]


def agent_command(spec: RunSpec, agent_id: int, zenoh: ZenohOptions, extra=(), python: str | None = None) -> list:
    """argv of agent ``agent_id``."""
    return [python or sys.executable, "-m", AGENT_MODULE, "--id", str(agent_id), *spec.to_argv(),
            *zenoh.to_argv(), *extra]
