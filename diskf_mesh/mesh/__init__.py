"""mesh: what the agent and world processes are made of, in rooms from the bottom up.

    wire        what travels and where: the msgpack codec, the key space, the counters reports carry
    security    who may speak: per-run credentials, access control (and its simulated enforcement)
    protocol    the sans-I/O machines (world, agent) and what they call: receive path, guard, inbox,
                the agent's estimator, verdicts, a run's status at its end
    process     one OS process: the zenoh transport, its settings, the shell on the wall clock, signals,
                command lines; its docstring follows one tick through the mesh
    simulated   the seeded simulated network and a whole run on it

A room may import the rooms listed before it, never one after (tests/test_layers.py).

The processes themselves are ``sim.world`` (ground truth, lockstep or on the clock),
``agents.agent`` (one agent) and ``sim.launcher`` (``diskf-mesh up``).

May import: core, estimators, data, engine.
"""
