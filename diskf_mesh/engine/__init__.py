"""engine: every agent of every seed at once, in one process.

    batch        the batched tick loop (dense and gathered message layouts)
    oracle       the same estimators as plain per-agent loops (the tests' twin)
    centralized  the centralized filter over all agents, a reference bound

May import: core, estimators, data.
"""
