"""mesh: what the agent and world processes are made of.

    keys, wire     the key space and the msgpack messages (one parse per key, one decode per message)
    transport      Transport: zenoh sessions (the tests have an in-process bus of their own)
    zenoh_config   session settings (TLS, access control, endpoints)
    credentials    the per-run CA and certificates
    guard          the fusion guard (a message's values before it may be fused)
    receive        an agent's receive path: gate -> guard -> faults -> inbox
    inbox          the one place a neighbour's message waits (for its tick, for fusion)
    delayline, counters   the simulated links' delays, the counts
    process        a mesh process (a machine in a shell), and one tick through the mesh
    events         the sans-I/O boundary: events into a protocol machine, effects out
    agent_machine  an agent's protocol: one tick in order (open, collect, close), joining, rejoining
    world_machine  the world's protocol: ticks, reports, liveliness, pauses, the rejoin answers
    shell          runs a machine over a Transport on the wall clock (one lock, timers, Woke)
    rejoin         where a (re)joining agent starts: a neighbour's fused estimate, or the prior
    verdicts       what an agent reports about each tick's messages (fused, lost, late, rejected)
    run_status     a run's status at its end (exact, as planned, degraded, diverged, incomplete), by the engine
    simnet, schedule, access   the simulated network: links, pauses, crashes, leases on a seeded
                   virtual clock; its event queue; the credentials' access rules it enforces
    simrun         a whole run (the world and every agent's machine) on the simulated network
    stopping       how a mesh process stops on a signal
    estimator      an agent's estimator: the engine's functions on a batch of one
    reports        what a run's reports said (the world's record and a recording extend it)
    runspec        one run's settings as command lines (launcher, compose)
    clock          real-time mode (--rate): the world's clock, the agents' deadline, misses
    log, profile   logging and per-phase timing

The processes themselves are ``sim.world`` (ground truth, lockstep or on the clock),
``agents.agent`` (one agent) and ``sim.launcher`` (``diskf-mesh up``).

May import: core, estimators, data, engine.
"""
