"""How an agent picks up a run in progress.

An agent process that was killed and started again with the same id (or one
that fell out of the run: frozen past zenoh's lease) finds the world already
ticking. It declares itself ready at once (it does not wait for every agent,
some may be gone), and joins at the first tick J at which the world counts
it live. Before its local step of tick J it asks the world (a query on
``Keys.start``, payload ``wire.encode_join``) for the estimate x_bar, P_bar
of tick J - 1 to start from, and the world answers (``wire.encode_start``):

* **a neighbour's fused estimate** (our choice): of the agents linked to it
  at tick J - 1 (within range: ``in_range``, which follows from the
  scenario's motion alone) that reported tick J - 1, the one with the
  smallest trace(P_bar), the most certain (``most_certain``). Within range,
  this is what a freshly started node could ask a neighbour for; it starts
  the agent where the network already is. The agent resets its observation
  window (``AgentEstimator``'s ``start``).
* **its prior** (x0, P0), as a fresh agent at tick 1, when no linked agent
  reported tick J - 1 (it rejoined alone). In a moving-target scenario the
  prior is far from the truth and P0 does not say so: that agent's error
  is large until measurements and neighbours pull it back.

The answer passes the guard's checks before it is used (``decode_start``:
finite, positive definite, magnitude, conditioning); one that fails leaves
the agent at its prior. No answer is asked again (``agent_machine.ASK_S``
later): a world that is frozen answers once it runs again, and the prior
stays the world's answer, never the agent's guess. Only the world reads
reports: the agent never listens to its neighbours' reports.

Why not always the prior: DISKF agents publish their prediction x^, which
the state compensation and the baselines' consensus steps pull neighbours
towards; a confident wrong prior would drag the neighbours too.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.mesh.protocol.estimator import neighbours


def in_range(scn, agent_id: int, tick: int) -> set:
    """The agents linked to ``agent_id`` at ``tick`` (itself not included),
    from the scenario's positions at that tick: the same positions the
    world's tick carries (``Scenario.positions``)."""
    return set(neighbours(scn, agent_id, scn.positions(tick)[tick - 1])) - {agent_id}


def most_certain(reports: dict, linked):
    """Of ``reports`` {sender: an estimate with ``P``}, the sender in
    ``linked`` with the smallest trace(P) (ties: the smaller id), or None."""
    linked = set(linked)
    usable = [(float(np.trace(r.P)), s) for s, r in sorted(reports.items()) if s in linked]
    return min(usable)[1] if usable else None
