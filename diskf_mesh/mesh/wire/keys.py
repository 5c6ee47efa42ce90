"""The key space of one mesh run.

Everything a run publishes lives under ``diskf/<run-id>/``, so two runs on one
network never see each other's traffic (a run id is 1 to 32 characters of
letters, digits, ``-`` and ``_``):

    diskf/<run>/world/tick             world -> all      opens tick k: positions of every
                                                         agent, the live set ("tick")
    diskf/<run>/world/meas/<id>        world -> agent id its own measurement at tick k, or
                                                         none ("meas")
    diskf/<run>/world/stop             world -> all      the run is over ("stop")
    diskf/<run>/agent/<id>/msg/<to>    agent -> agents   its one message of tick k ("msg"),
                                                         addressed to the agents in range
                                                         (``<to>`` = ``_3_7_``: ids between
                                                         underscores; ``_`` for none)
    diskf/<run>/agent/<id>/msg         no address: no agent subscribes to it (a watcher of
                                                         ``msgs`` sees it; "msg")
    diskf/<run>/agent/<id>/report      agent -> world    its fused estimate of tick k ("report")
    diskf/<run>/agent/<id>/duplicate   agent -> world    a second process of this id, leaving; the
                                                         payload is its nonce ("duplicate")
    diskf/<run>/agent/<id>/stopped     agent -> world    it stops before the run's end, and why
                                                         (its estimator diverged, it was
                                                         interrupted): a "stop" payload ("stopped")
    diskf/<run>/start/<id>             query, agent -> world: agent id (re)joins at tick J; the
                                                         world answers with the estimate it
                                                         starts from ("start")
    diskf/<run>/alive/world/<nonce>    liveliness token  the world is up
    diskf/<run>/ticking/world          liveliness token  the world has started tick 1: an agent
                                                         that sees it before it is ready is a
                                                         restart joining a run in progress
    diskf/<run>/alive/agent/<id>/<nonce>  liveliness     agent id is up and subscribed
    diskf/<run>/ready/agent/<id>/<nonce>  liveliness     agent id sees the world and every other
                                                         agent of the scenario (so its message
                                                         reaches them all); the world starts
                                                         tick 1 once every agent is ready

Every process's tokens end in its own ``<nonce>`` (``new_nonce``: its start
time in nanoseconds, 16 hex digits, then 8 random hex digits), so two
processes holding one id (or two worlds of one run id) hold two distinct
tokens and everyone sees both: a process that finds a token of its id before
declaring its own is the second and leaves (exit 2); two that declared at
the same moment compare nonces, and the larger (the later start) leaves,
unless the run was already ticking: then the one that found the run in
progress leaves whatever the nonces (the other has worked since tick 1;
the world's answer to its start query names the processes holding the id).
A ready token's nonce has a join count after a dot (``<nonce>.<n>``): an
agent that fell out of the run (frozen past zenoh's lease) withdraws it and
declares the next to rejoin.

An agent publishes its one message of a tick on a key that names the agents
in range at that tick (it knows every position and the live set from the
world's tick) and subscribes to ``agent/*/msg/$*_<its id>_$*`` (zenoh's
sub-chunk wildcard): zenoh then routes the message to those agents only,
and an agent out of range never spends a wake-up on it. The address only
saves work; every receiver still gates by range itself.

Payload formats are in ``diskf_mesh.mesh.wire.codec``. The id in a key must equal the id
in the payload; a receiver rejects a message whose key names another agent.
"""
from __future__ import annotations

import functools
import re
import secrets
import sys
import time
from dataclasses import dataclass

from diskf_mesh.core.errors import InputError

PREFIX = "diskf"
CACHED_KEY = 512  # longest key whose parse is remembered (4,096 of them at most)
_RUN_ID = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


def new_nonce() -> str:
    """This process's token suffix: start time (ns, hex) then random, so that
    nonces sort by start and two processes never share one."""
    return f"{time.time_ns():016x}{secrets.token_hex(4)}"


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
    def msg(self, agent, to=None) -> str:
        """Agent ``agent``'s message key; with ``to`` (ids), addressed to those."""
        key = f"{self.root}/agent/{agent}/msg"
        return key if to is None else f"{key}/{address(to)}"

    def msg_to(self, agent) -> str:
        """The messages addressed to ``agent``, from any agent."""
        return f"{self.root}/agent/*/msg/$*_{int(agent)}_$*"

    @property
    def msgs(self) -> str:
        """Every agent message of the run, addressed or not (to watch the wire)."""
        return f"{self.root}/agent/*/msg/**"

    def report(self, agent) -> str:
        return f"{self.root}/agent/{agent}/report"


    def duplicate(self, agent) -> str:
        return f"{self.root}/agent/{agent}/duplicate"

    def stopped(self, agent) -> str:
        return f"{self.root}/agent/{agent}/stopped"

    def start(self, agent) -> str:
        """The key of agent ``agent``'s query for its starting estimate
        (``"*"``: the world's queryable of every agent's)."""
        return f"{self.root}/start/{agent}"

    # liveliness (``nonce="*"``: the expression of every process's token)
    @property
    def alive_world(self) -> str:
        """Every world token of the run (``world(nonce)``: one world's)."""
        return self.world("*")

    def world(self, nonce: str) -> str:
        return f"{self.root}/alive/world/{nonce}"

    @property
    def ticking(self) -> str:
        return f"{self.root}/ticking/world"

    def alive(self, agent, nonce: str = "*") -> str:
        return f"{self.root}/alive/agent/{agent}/{nonce}"

    def ready(self, agent, nonce: str = "*") -> str:
        return f"{self.root}/ready/agent/{agent}/{nonce}"

    def parse(self, key: str) -> tuple:
        """(kind, agent id or None) of a key of this run; kind is one of tick,
        meas, stop, msg, report, duplicate, stopped, start, alive-world, ticking,
        alive, ready, or None (foreign). A token's nonce is ``nonce(key)``.
        An id that is not an integer gives (kind, None). Remembered: a run
        uses few distinct keys, and every message's key is parsed (keys
        longer than ``CACHED_KEY`` are not, so what an intruder's keys can
        hold in the cache stays small)."""
        return _parse(self.root, key) if len(key) <= CACHED_KEY else _parse.__wrapped__(self.root, key)


@functools.lru_cache(maxsize=1 << 16)  # a few keys per agent: a simulated run's thousands of agents share it
def _parse(root: str, key: str) -> tuple:
    root = root + "/"
    if not key.startswith(root):
        return None, None
    parts = key[len(root):].split("/")
    if len(parts) == 4 and parts[0] == "agent" and parts[2] == "msg" and _ADDRESS.match(parts[3]):
        parts = parts[:3]  # the address does not change the kind or the sender
    at, last = _ID_POS.get((parts[0], len(parts))), _NONCE_POS.get((parts[0], len(parts)))
    shape = tuple("#" if i == at else "*" if i == last and p else p for i, p in enumerate(parts))
    kind = _SHAPES.get(shape)
    if kind is None:
        return None, None
    if at is None:
        return kind, None
    try:
        return kind, int(parts[at])
    except ValueError:
        return kind, None


def nonce(key: str) -> str:
    """The nonce a token key ends with (interned: a process's nonce is held by every other)."""
    return sys.intern(key.rsplit("/", 1)[-1])


def address(ids) -> str:
    """The address chunk of a message key: ``_3_7_`` for ids 3 and 7, ``_`` for none."""
    return "_" + "".join(map("{}_".format, map(int, sorted(ids))))


_ADDRESS = re.compile(r"^_(?:\d+_)*$")

# shape of a key below the run root -> kind; "#" stands for an agent id
_SHAPES = {
    ("world", "tick"): "tick",
    ("world", "meas", "#"): "meas",
    ("world", "stop"): "stop",
    ("agent", "#", "msg"): "msg",
    ("agent", "#", "report"): "report",
    ("agent", "#", "duplicate"): "duplicate",
    ("agent", "#", "stopped"): "stopped",
    ("start", "#"): "start",
    ("alive", "world", "*"): "alive-world",
    ("ticking", "world"): "ticking",
    ("alive", "agent", "#", "*"): "alive",
    ("ready", "agent", "#", "*"): "ready",
}
# (first segment, segment count) -> index of the id segment
_ID_POS = {("world", 3): 2, ("agent", 3): 1, ("alive", 4): 2, ("ready", 4): 2, ("start", 2): 1}
_NONCE_POS = {("alive", 3): 2, ("alive", 4): 3, ("ready", 4): 3}  # "*" in _SHAPES: any nonce


def _pattern(expr: str) -> str:
    """The regular expression of a key expression: ``**`` any chunks (none
    too), ``*`` one chunk, ``$*`` any characters within a chunk."""
    chunks = []
    for c in expr.split("/"):
        if not (c == "**" and chunks and chunks[-1] == "**"):  # "**/**" is "**"
            chunks.append(c)
    if chunks == ["**"]:
        return ".*"
    out, lead = "", True  # lead: the next chunk needs no '/' before it
    for i, c in enumerate(chunks):
        if c == "**":
            out += "(?:[^/]+/)*" if i == 0 else "(?:/[^/]+)*"
            lead = i == 0
            continue
        piece = "[^/]*" if c == "*" else "[^/]*".join(map(re.escape, c.split("$*")))
        out += piece if lead else "/" + piece
        lead = False
    return out


@functools.lru_cache(maxsize=1 << 16)  # a run's expressions: a few per agent
def matcher(expr: str):
    """``fullmatch`` of a key expression's compiled pattern: ``matcher(e)(key)``
    is truthy where zenoh's ``KeyExpr(e).includes(key)`` is (for keys and
    for expressions matched chunk for chunk), None where not. An
    expression ``head/**`` or ``head/*`` whose head has no wildcard (each
    agent's own keys and tokens) is matched as the head and what follows
    it, without compiling a pattern."""
    head, _, last = expr.rpartition("/")
    if last in ("**", "*") and head and "*" not in head and "$" not in head:
        return functools.partial(_below if last == "**" else _one_below, head, head + "/")
    return re.compile(_pattern(expr)).fullmatch


def _below(head: str, prefix: str, key: str):
    """True where ``key`` is ``head`` or ``head`` then non-empty chunks (the
    pattern of ``head/**``), None where not."""
    if key == head:
        return True
    if not key.startswith(prefix):
        return None
    rest = key[len(prefix):]
    return True if rest and rest[0] != "/" and rest[-1] != "/" and "//" not in rest else None


def _one_below(head: str, prefix: str, key: str):
    """True where ``key`` is ``head`` and one chunk more (the pattern of
    ``head/*``), None where not."""
    return True if key.startswith(prefix) and "/" not in key[len(prefix):] else None


def key_matches(expr: str, key: str) -> bool:
    return matcher(expr)(key) is not None
