"""mesh: what the agent and world processes are made of.

    keys, wire     the key space and the msgpack messages (one parse per key, one decode per message)
    transport      Transport: zenoh sessions, and an in-process bus for tests
    zenoh_config   session settings (TLS, access control, endpoints)
    credentials    the per-run CA and certificates
    guard          the fusion guard (a message's values before it may be fused)
    receive        an agent's receive path: gate -> guard -> faults -> inbox
    inbox          the one place a neighbour's message waits (for its tick, for fusion)
    delayline, counters   the simulated links' delays, the counts
    process        the skeleton of the world and agent processes, and one tick through the mesh
    estimator      an agent's estimator: the engine's functions on a batch of one
    reports        what a run's reports said (the world's record and a recording extend it)
    runspec        one run's settings as command lines (launcher, compose)
    clock          real-time mode (--rate): the world's clock, the agents' deadline, misses
    log, profile   logging and per-phase timing

The processes themselves are ``sim.world`` (ground truth, lockstep or on the clock),
``agents.agent`` (one agent) and ``sim.launcher`` (``diskf-mesh up``).

May import: core, estimators, data, engine.
"""
