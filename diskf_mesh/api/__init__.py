"""api: the public Python interface, re-exported by ``diskf_mesh`` itself.

    results   the result types (dataclasses of numpy arrays, with ``to_dict``)
    calls     load_scenario, simulate, estimate, run, experiment, replay,
              read_trace, write_trace, up
    streaming Network and Agent: one tick at a time (``Estimate`` per tick)

Reference: docs/api.md. Every call takes and returns plain values (paths,
names, numpy arrays, dataclasses); bad input raises ``InputError`` naming
the field, as the command line's one ``error:`` line does.

May import: every layer below it (core ... cli).
"""
from __future__ import annotations

from diskf_mesh.api.calls import (
    estimate,
    estimator_names,
    experiment,
    load_scenario,
    read_trace,
    replay,
    run,
    simulate,
    up,
    write_trace,
)
from diskf_mesh.api.results import Experiment, MeshRun, Run
from diskf_mesh.api.streaming import Agent, Estimate, Network

__all__ = ["load_scenario", "simulate", "estimate", "run", "experiment", "replay", "up", "read_trace",
           "write_trace", "estimator_names", "Run", "Experiment", "MeshRun", "Network", "Agent", "Estimate"]
