"""mesh.simulated: every process of a run in one Python process, on a seeded virtual clock (docs/simnet.md).

    simnet     the network: links, pauses, crashes, leases; the access rules enforced
    schedule   its virtual clock and deterministic event queue
    simrun     a whole run (the world and every agent's machine) on the simulated network

May import: core, estimators, data, engine, mesh.wire, mesh.security, mesh.protocol.
"""
