"""diskf-mesh: decentralized input and state estimation (DISKF) on a
peer-to-peer mesh of agent processes.

The Python API (docs/api.md), loaded on first use so that ``import
diskf_mesh`` stays cheap for the processes of a run::

    import diskf_mesh
    scn = diskf_mesh.load_scenario("dynamic")                 # or a path to your TOML
    res = diskf_mesh.experiment(scn, "diskf,kcf", seeds=5)    # Table II's shape
    print(res.table())
    run = diskf_mesh.run(scn, "diskf-r", seeds=[0, 1])        # estimates as numpy arrays
    run.x.shape, run.metrics["mae_state"]
    net = diskf_mesh.Network(scn)                              # one tick at a time, from your own loop
    est = net.step(measurements, links=links)                  # every agent's x, P, d

Layers, bottom to top (each folder's docstring says what lives there;
a module imports its own layer and those below, ``tests/test_layers.py``):

    core        the paper's equations and the model (numpy only)
    estimators  DISKF, DISKF-R and the baselines (plugins: docs/estimators.md)
    data        scenarios, traces, faults, metrics, output files, provenance
    engine      all agents and seeds at once; the plain oracle; the centralized bound
    mesh        the pieces of the agent and world processes (wire, keys, transport, guard)
    studies     experiments, the report's studies, figures
    recording   MCAP recordings of mesh runs
    live        the live view in a browser
    cli         the diskf-mesh command line
    api         the Python API re-exported here

The processes: ``agents/agent.py`` (one agent), ``sim/world.py`` (ground
truth, lockstep) and ``sim/launcher.py`` (``diskf-mesh up``).
"""
from __future__ import annotations

TYPE_CHECKING = False  # typing's constant, without importing typing: the processes of a run import this first

__version__ = "0.1.0"

API = ("load_scenario", "simulate", "estimate", "run", "experiment", "replay", "up", "read_trace", "write_trace",
       "estimator_names", "Run", "Experiment", "MeshRun", "Network", "Agent", "Estimate", "InputError")
__all__ = ["__version__", *API]

if TYPE_CHECKING:  # what type checkers and IDEs see; at run time __getattr__ loads it on first use
    from diskf_mesh.api import (Agent, Estimate, Experiment, MeshRun, Network, Run, estimate, estimator_names,
                                experiment, load_scenario, read_trace, replay, run, simulate, up, write_trace)
    from diskf_mesh.core.errors import InputError


def __getattr__(name: str) -> object:
    if name == "InputError":
        from diskf_mesh.core.errors import InputError

        return InputError
    if name in API:
        from diskf_mesh import api

        return getattr(api, name)
    raise AttributeError(f"module 'diskf_mesh' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The API and the module's own dunders: no helper names."""
    return sorted([*(n for n in globals() if n.startswith("__")), *API])
