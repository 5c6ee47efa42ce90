"""mesh.wire: what travels between the processes of a run, and where.

    codec      the msgpack messages (one decode per message): measurement, tick, message, report, ...
    keys       the key space of one run (one parse per key)
    counters   what one agent did with the messages of a run (its fields travel in each report)

May import: core, estimators, data, engine.
"""
