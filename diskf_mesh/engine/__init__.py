"""engine: every agent of every seed at once, in one process.

    batch        the batched tick loop (dense and gathered message layouts)
    oracle       the same estimators as plain per-agent loops (the tests' twin)
    centralized  the centralized filter over all agents, a reference bound
    verify       a run checked against its replay: what each agent fused, its restarts, every estimate and
                 fused message's digest bit for bit -> exact, as planned, degraded, diverged or incomplete

May import: core, estimators, data.
"""
