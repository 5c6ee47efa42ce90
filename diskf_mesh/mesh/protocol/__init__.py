"""mesh.protocol: the sans-I/O protocol machines and everything they call (no thread, no socket, no clock read).

    events         the boundary: events into a protocol machine, effects out
    intake         an agent's edge: a sample read once into a typed event (key parsed, payload decoded)
    agent_machine  an agent's protocol: one tick in order (open, collect, close), joining, rejoining
    world_machine  the world's protocol: ticks, reports, liveliness, pauses, the rejoin answers
    receive        an agent's receive path: guard -> gate -> faults -> inbox (the one place a message waits)
    guard          the fusion guard (a message's values before it may be fused)
    delayline      the links' delayed copies
    estimator      an agent's estimator: the engine's functions on a batch of one
    rejoin         where a (re)joining agent starts: a neighbour's fused estimate, or the prior
    verdicts       what an agent reports about each tick's messages (fused, lost, late, rejected)
    reports        what a run's reports said (the world's record and a recording extend it)
    run_status     a run's status at its end (exact, as planned, degraded, diverged, incomplete), by the engine
    clock          real-time mode (--rate): the world's clock, the agents' deadline, misses
    log, profile   logging and per-phase timing

May import: core, estimators, data, engine, mesh.wire, mesh.security.
"""
