"""The key space of one mesh run.

Everything a run publishes lives under ``diskf/<run-id>/``, so two runs on one
network never see each other's traffic (a run id is 1 to 32 characters of
letters, digits, ``-`` and ``_``):

    diskf/<run>/world/tick             world -> all      opens tick k: positions of every
                                                         agent, the live set ("tick")
    diskf/<run>/world/meas/<id>        world -> agent id its own measurement at tick k, or
                                                         none ("meas")
    diskf/<run>/world/stop             world -> all      the run is over ("stop")
    diskf/<run>/agent/<id>/msg         agent -> agents   its one message of tick k ("msg")
    diskf/<run>/agent/<id>/report      agent -> world    its fused estimate of tick k ("report")
    diskf/<run>/alive/world            liveliness token  the world is up
    diskf/<run>/ticking/world          liveliness token  the world has started tick 1: an agent
                                                         that sees it before it is ready is a
                                                         restart joining a run in progress
    diskf/<run>/alive/agent/<id>       liveliness token  agent id is up and subscribed
    diskf/<run>/ready/agent/<id>       liveliness token  agent id sees the world and every other
                                                         agent of the scenario (so its message
                                                         reaches them all); the world starts
                                                         tick 1 once every agent is ready

Payload formats are in ``diskf_mesh.wire``. The id in a key must equal the id
in the payload; a receiver rejects a message whose key names another agent.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from ..errors import InputError

PREFIX = "diskf"
_RUN_ID = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


def check_run_id(run_id: str) -> str:
    if not isinstance(run_id, str) or not _RUN_ID.match(run_id):
        raise InputError("run-id", f"must be 1 to 32 letters, digits, '-' or '_', got {run_id!r}")
    return run_id


@dataclass(frozen=True)
class Keys:
    run_id: str

    def __post_init__(self):
        check_run_id(self.run_id)

    @property
    def root(self) -> str:
        return f"{PREFIX}/{self.run_id}"

    # world -> agents
    @property
    def tick(self) -> str:
        return f"{self.root}/world/tick"

    def meas(self, agent: int) -> str:
        return f"{self.root}/world/meas/{int(agent)}"

    @property
    def stop(self) -> str:
        return f"{self.root}/world/stop"

    # agents -> agents, agents -> world
    def msg(self, agent) -> str:
        return f"{self.root}/agent/{agent}/msg"

    def report(self, agent) -> str:
        return f"{self.root}/agent/{agent}/report"

    # liveliness
    @property
    def alive_world(self) -> str:
        return f"{self.root}/alive/world"

    @property
    def ticking(self) -> str:
        return f"{self.root}/ticking/world"

    def alive(self, agent) -> str:
        return f"{self.root}/alive/agent/{agent}"

    def ready(self, agent) -> str:
        return f"{self.root}/ready/agent/{agent}"

    @property
    def tokens(self) -> str:
        """Every liveliness token of the run (alive and ready)."""
        return f"{self.root}/*/**"

    def parse(self, key: str) -> tuple:
        """(kind, agent id or None) of a key of this run; kind is one of tick,
        meas, stop, msg, report, alive-world, alive, ready, or None (foreign).
        An id that is not an integer gives (kind, None)."""
        root = self.root + "/"
        if not key.startswith(root):
            return None, None
        parts = key[len(root):].split("/")
        shape = tuple("#" if i == _ID_POS.get((parts[0], len(parts))) else p for i, p in enumerate(parts))
        kind = _SHAPES.get(shape)
        if kind is None:
            return None, None
        pos = _ID_POS.get((parts[0], len(parts)))
        if pos is None:
            return kind, None
        try:
            return kind, int(parts[pos])
        except ValueError:
            return kind, None


# shape of a key below the run root -> kind; "#" stands for an agent id
_SHAPES = {
    ("world", "tick"): "tick",
    ("world", "meas", "#"): "meas",
    ("world", "stop"): "stop",
    ("agent", "#", "msg"): "msg",
    ("agent", "#", "report"): "report",
    ("alive", "world"): "alive-world",
    ("ticking", "world"): "ticking",
    ("alive", "agent", "#"): "alive",
    ("ready", "agent", "#"): "ready",
}
# (first segment, segment count) -> index of the id segment
_ID_POS = {("world", 3): 2, ("agent", 3): 1, ("alive", 3): 2, ("ready", 3): 2}
