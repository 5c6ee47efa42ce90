"""diskf-mesh: decentralized input and state estimation (DISKF) on a
peer-to-peer mesh of agent processes.

Layers, bottom to top (each folder's docstring says what lives there;
a module imports its own layer and those below, ``tests/test_layers.py``):

    core        the paper's equations and the model (numpy only)
    estimators  DISKF, DISKF-R and the baselines (plugins: docs/estimators.md)
    data        scenarios, traces, faults, metrics, output files
    engine      all agents and seeds at once; the plain oracle; the centralized bound
    mesh        the pieces of the agent and world processes (wire, keys, transport, guard)
    studies     experiments, the report's studies, figures
    recording   MCAP recordings of mesh runs
    live        the live view in a browser
    cli         the diskf-mesh command line

The processes: ``agents/agent.py`` (one agent), ``sim/world.py`` (ground
truth, lockstep) and ``sim/launcher.py`` (``diskf-mesh up``).
"""
__version__ = "0.1.0"
