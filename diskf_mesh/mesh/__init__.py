"""The Zenoh mesh: wire keys, zenoh settings, transport, and the glue that lets
an agent process run the engine's estimator on a batch of one.

The processes themselves live in ``sim.world`` (ground truth, lockstep),
``agents.agent`` (one agent) and ``sim.launcher`` (``diskf-mesh up``).
"""
