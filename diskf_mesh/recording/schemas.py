"""The channels of a recording and the JSON Schema of each (MCAP schema
encoding ``jsonschema``, message encoding ``json``: Foxglove and the ``mcap``
tools read them without plugins).

Every message carries ``tick`` (k >= 1); there is one message per channel
and tick, holding every agent's (a list; in Foxglove, pick one agent with a
filter, e.g. ``/agents/estimates.estimates[:]{agent==3}.position_error``).
Vectors are JSON arrays of numbers, matrices arrays of rows. Agent ids are
the scenario's, integers or names ("drone-1"), as the user gave them.
"""
from __future__ import annotations

import json

SCHEMA_PREFIX = "diskf."

_NUM = {"type": "number"}
_INT = {"type": "integer"}
_ID = {"type": ["integer", "string"], "description": "an agent id as the scenario gave it"}
_IDS = {"type": "array", "items": _ID}
_VEC = {"type": "array", "items": _NUM}
_MAT = {"type": "array", "items": _VEC}


def _obj(title: str, description: str, required=(), **props) -> dict:
    return {"title": SCHEMA_PREFIX + title, "description": description, "type": "object",
            "properties": props, "required": list(required or props)}


_TICK = {"tick": {**_INT, "minimum": 1, "description": "tick k (1..K)"}}

# topic -> JSON Schema of its messages
CHANNELS = {
    "/run": _obj("Run", "what ran: scenario, seed, estimator, faults, ids, dimensions, versions, provenance (once, first)",
                 required=("format", "run_id", "scenario", "seed", "algorithm", "ids", "ticks"),
                 format={"type": "string"}, run_id={"type": "string"}, scenario={"type": "string"},
                 scenario_name={"type": "string"}, seed=_INT, algorithm={"type": "string"},
                 topology={"type": "string"}, comm_range={"type": ["number", "string"]},
                 ids=_IDS, ticks=_INT, n=_INT, m=_INT, params={"type": "object"}, faults={"type": "object"},
                 tick_period_s=_NUM, versions={"type": "object"},
                 provenance={"type": ["object", "null"],
                             "description": "what made the run (diskf_mesh.data.provenance: command, scenario and "
                                            "its hash, seeds, ticks, estimator, settings, faults, versions, git "
                                            "commit, start time)"}),
    "/world/truth": _obj("Truth", "ground truth of tick k: the target's state x and the input d acting "
                                  "between tick k-1 and k", **_TICK, x=_VEC, d=_VEC, position=_VEC),
    "/world/agents": _obj("Agents", "every agent's position at tick k (scenario order) and the live set",
                          **_TICK, ids=_IDS, positions=_MAT, live=_IDS),
    "/world/links": _obj("Links", "the link graph of tick k: pairs [a, b] (a < b) of live agents in range",
                         **_TICK, edges={"type": "array", "items": _IDS}),
    "/world/tick": _obj("TickClosed", "tick k is over: who reported, who did not (written last; a tick "
                                      "without it is incomplete)", **_TICK, reported=_IDS, missing=_IDS,
                        wall_s={**_NUM, "description": "seconds since tick 1 opened"}),
    "/agents/sent": _obj("MessagesSent", "every agent message of tick k, named by the digest of the bytes it "
                                         "published (its report carries the digest, never the message)", **_TICK,
                         messages={"type": "array", "items": _obj(
        "MessageSent", "one agent message", required=("tick", "sender", "to", "digest"), **_TICK, sender=_ID,
        to={**_IDS, "description": "the agents it is addressed to (in range at its tick)"},
        digest={"type": "string", "description": "hex digest of the payload it published "
                                                 "(diskf_mesh.mesh.wire.codec.digest)"},
        differs={**_IDS, "description": "receivers that fused a message of this sender and tick with another "
                                        "digest (not what it sent)"})}),
    "/agents/delivered": _obj("MessagesDelivered", "what became of every message of tick k at every receiver "
                                                   "linked to its sender", **_TICK, deliveries={"type": "array", "items": _obj(
        "MessageDelivered", "sender's message of tick k at one receiver",
        required=("sender", "receiver", "verdict", "copies"), sender=_ID, receiver=_ID,
        verdict={"enum": ["fused", "lost", "late", "rejected", "unreported"],
                 "description": "fused; lost (the link dropped it); late (no copy by the tick's close); "
                                "rejected (reason); unreported (the receiver sent no report of tick k)"},
        reason={"type": "string"},
        copies={**_INT, "description": "copies the seeded fault layer sends (0: lost; 2: one is a duplicate)"},
        delays_ms={**_VEC, "description": "each copy's delay planned by the fault layer"})}),
    "/agents/estimates": _obj("Estimates", "every agent's fused estimate after tick k, as reported to the world",
                              **_TICK, estimates={"type": "array", "items": _obj(
        "Estimate", "one agent's", required=("agent", "x", "P", "d_valid", "fused"), agent=_ID,
        x=_VEC, P=_MAT, d={"type": ["array", "null"], "items": _NUM}, d_valid={"type": "boolean"}, fused=_IDS,
        digests={"type": "array", "items": {"type": "string"}, "description": "per sender of fused, in order: "
                 "the hex digest of its message as fused (diskf_mesh.mesh.wire.codec.message_digest)"},
        position_error={**_NUM, "description": "distance of the estimated position to the truth"})}),
    "/agents/counters": _obj("Counters", "every agent's message counters after tick k (diskf_mesh.mesh.wire.counters), flat",
                             **_TICK, counters={"type": "array", "items": _obj(
        "AgentCounters", "one agent's", agent=_ID, counters={"type": "object", "additionalProperties": _INT})}),
    "/run/result": _obj("Result", "the run's end: status, ticks closed, metrics, the run checked by the "
                                  "engine (last)",
                        required=("status", "ticks"), status={"type": "string"}, ticks=_INT,
                        metrics={"type": "object", "description": "the run's metrics; a real-time run's "
                                 "rate_hz, deadline_s, deadline_misses and tick_period with them"},
                        verification={"type": "object", "description": "the end-of-run replay on the engine "
                                      "(diskf_mesh.engine.verify): status (exact, as planned, degraded, diverged, "
                                      "incomplete), reason, its evidence, and the restarts it replayed (tick, "
                                      "agent, source, the starting x and P the world handed it)"}),
}


def schema_bytes(topic: str) -> bytes:
    return json.dumps(CHANNELS[topic], sort_keys=True).encode()
