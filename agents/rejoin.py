"""How a restarted agent picks up a run in progress.

An agent process that was killed and started again with the same id finds
the world already ticking. It declares itself ready at once (it does not wait
for every agent, some may be gone), and the world counts it live from its
next tick k1 on. Before its first tick the agent re-initialises its fused
estimate x_bar, P_bar of tick k1 - 1:

* **from a neighbour's fused estimate** (our choice): the reports of tick
  k1 - 1 that the agents linked to it at that tick (within range, alive) sent
  to the world, which a rejoining agent listens to. Who was in range follows
  from the scenario alone (motion is a function of the tick: ``in_range``),
  who was alive from who reported; so the agent needs no message of the
  world from before it joined. It takes the one with the smallest
  trace(P_bar), the most certain, and resets its observation window. Within
  range, this is what a freshly started node could ask a neighbour for; it
  starts the agent where the network already is. The world counts a
  rejoining agent live from its tick after next once it sees the agent
  ready, so the reports of tick k1 - 1 are sent after the agent subscribed.
* **from its prior** (x0, P0), as a fresh agent at tick 1, when no linked
  agent reported tick k1 - 1 (it rejoined alone). In a moving-target
  scenario the prior is far from the truth and P0 does not say so: that
  agent's error is large until measurements and neighbours pull it back.

Why not always the prior: DISKF agents publish their prediction x^, which
the state compensation and the baselines' consensus steps pull neighbours
towards; a confident wrong prior would drag the neighbours too.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from diskf_mesh.mesh.estimator import neighbours


def in_range(scn, agent_id: int, tick: int) -> set:
    """The agents linked to ``agent_id`` at ``tick`` (itself not included),
    from the scenario's positions at that tick: the same positions the
    world's tick carries (``Scenario.positions``)."""
    return set(neighbours(scn, agent_id, scn.positions(tick)[tick - 1])) - {agent_id}


def reinitialise(est, reports: dict, linked) -> int | None:
    """Set ``est.state`` (an ``AgentEstimator``) from the most certain of
    ``reports`` {sender: wire.Report} whose sender is in ``linked``; returns
    that sender, or None (state left at the prior)."""
    usable = [r for s, r in sorted(reports.items()) if s in set(linked)]
    if not usable:
        return None
    best = min(usable, key=lambda r: (float(np.trace(r.P)), r.sender))
    st = est.state
    est.state = replace(st, x=np.array(best.x, dtype=float).reshape(st.x.shape),
                        P=np.array(best.P, dtype=float).reshape(st.P.shape), since=np.zeros_like(st.since))
    return best.sender
