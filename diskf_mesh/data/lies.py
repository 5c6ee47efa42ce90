"""Lies: chosen agents (insiders) send false messages from a chosen tick.

A lie is a fault an agent commits on its own outgoing message, planned like
the link faults (``data.faults``): in a scenario's ``[[faults.lies]]`` tables
or with ``--lie`` on the command line (one flag per lie, ``key=value``
pairs). The sending side applies it, so the in-process engine
(``engine.batch.run(lies=...)``), the simulated network and an agent process
(``mesh.protocol.agent_machine``) send the same bits, and mesh == engine
holds for a lying run too. The liar's own estimator stays honest: it fuses
its own true message; only what it sends (and, with ``reports = "lying"``,
what it reports to the world) is false.

    kind     what the liar sends at a lying tick k (size: ``size``)
    offset   its estimate moved by ``size`` (x^ and x~ shifted by ``size``
             along the diagonal of the position axes: ``size`` metres away)
    drift    moved by ``size`` per tick since ``from``: a slow drift
    shrink   its covariances times ``scale`` (default 1e-3) and moved by
             ``size``: a certain-looking small lie
    stale    its message of ``size`` ticks before (tick 1's while there is
             none that old): an old estimate replayed
    input    a false input: d = ``size`` in every component, marked valid,
             its covariance kept

    from     the first lying tick (default 1); until: the last (default: the end)
    on, off  lie ``on`` ticks, then tell the truth ``off`` ticks, repeated
             from ``from`` (default: always on)
    reports  "honest" (default): its reports carry its true estimate;
             "lying": its reports carry the same lie (moved, shrunk, stale or
             with the false input), consistent with its messages
    withhold a tick whose report the liar never sends (an agent process;
             the world then cannot know what it fused: ``engine.verify``'s
             ``unverifiable``)

Every change is element-wise arithmetic on the liar's arrays, the same
operation on the same operands wherever it runs.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from diskf_mesh.core.errors import InputError
from diskf_mesh.core.messages import Message, Output

KINDS = ("offset", "drift", "shrink", "stale", "input")
REPORTS = ("honest", "lying")
KEYS = ("agent", "kind", "size", "from", "until", "on", "off", "scale", "reports", "withhold")


@dataclass(frozen=True)
class Lie:
    """One agent's lie (module docstring). ``agent``: the scenario's id as
    the user wrote it (resolved to the run's id by ``resolve``)."""

    agent: int | str
    kind: str
    size: float
    start: int = 1
    until: int | None = None
    on: int | None = None
    off: int = 0
    scale: float = 1e-3
    reports: str = "honest"
    withhold: int | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise InputError("lie.kind", f"must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.reports not in REPORTS:
            raise InputError("lie.reports", f"must be one of {', '.join(REPORTS)}, got {self.reports!r}")
        if isinstance(self.size, bool) or not isinstance(self.size, (int, float)) or not math.isfinite(self.size):
            raise InputError("lie.size", f"must be a finite number, got {self.size!r}")
        if self.kind == "stale" and (self.size < 1 or int(self.size) != self.size):
            raise InputError("lie.size", f"of a stale lie is a whole number of ticks >= 1, got {self.size!r}")
        for name, low in (("start", 1), ("until", 1), ("on", 1), ("off", 0), ("withhold", 1)):
            v = getattr(self, name)
            if v is None and name in ("until", "on", "withhold"):
                continue
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                key = "from" if name == "start" else name
                raise InputError(f"lie.{key}", f"must be a whole number >= {low}, got {v!r}")
        if self.until is not None and self.until < self.start:
            raise InputError("lie.until", f"must be at least from ({self.start}), got {self.until}")
        if not (isinstance(self.scale, (int, float)) and not isinstance(self.scale, bool)
                and math.isfinite(self.scale) and self.scale > 0):
            raise InputError("lie.scale", f"must be a finite positive number, got {self.scale!r}")

    def lying(self, k: int) -> bool:
        """Whether the liar lies at tick ``k``."""
        if k < self.start or (self.until is not None and k > self.until):
            return False
        return self.on is None or (k - self.start) % (self.on + self.off) < self.on

    def shift(self, k: int) -> float:
        """How far (metres) the liar moves its estimate at tick ``k``."""
        if self.kind == "drift":
            return self.size * (k - self.start + 1)
        return self.size if self.kind in ("offset", "shrink") else 0.0

    @classmethod
    def from_mapping(cls, table: dict, where: str = "lie") -> "Lie":
        if not isinstance(table, dict):
            raise InputError(where, "must be a table")
        unknown = sorted(set(table) - set(KEYS))
        if unknown:
            raise InputError(f"{where}.{unknown[0]}", f"unknown lie setting; known: {', '.join(KEYS)}")
        for key in ("agent", "kind", "size"):
            if key not in table:
                raise InputError(f"{where}.{key}", "is required")
        given = {("start" if k == "from" else k): v for k, v in table.items()}
        if isinstance(given.get("size"), int) and not isinstance(given["size"], bool):
            given["size"] = float(given["size"])
        if isinstance(given.get("scale"), int) and not isinstance(given["scale"], bool):
            given["scale"] = float(given["scale"])
        try:
            return cls(**given)
        except InputError as e:
            raise InputError(f"{where}.{e.field.removeprefix('lie.')}", e.message) from None

    def to_mapping(self) -> dict:
        d = asdict(self)
        d["from"] = d.pop("start")
        return {k: d[k] for k in KEYS if d[k] is not None}

    def to_text(self) -> str:
        """The ``--lie`` value that gives this lie."""
        return ",".join(f"{k}={v}" for k, v in self.to_mapping().items())


def parse_text(text: str) -> Lie:
    """A ``--lie`` value: ``agent=3,kind=offset,size=200,from=50`` (the
    keys of a ``[[faults.lies]]`` table)."""
    table = {}
    for part in text.split(","):
        key, eq, value = part.strip().partition("=")
        if not eq or not key:
            raise InputError("lie", f"expected key=value pairs separated by commas, got {text!r}")
        table[key.strip()] = _value(value.strip())
    return Lie.from_mapping(table)


def _value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def resolve(lies, labels, ids) -> tuple:
    """The lies with each ``agent`` the run's id: ``labels`` are the agents'
    ids as the scenario gave them, ``ids`` the run's, in the same order.
    An agent not in the scenario is an InputError."""
    out = []
    for lie in lies:
        names = [str(x) for x in labels]
        if str(lie.agent) not in names:
            raise InputError("lie.agent", f"no agent {lie.agent!r} in the scenario (ids {', '.join(names)})")
        out.append(replace(lie, agent=ids[names.index(str(lie.agent))]))
    seen = [lie.agent for lie in out]
    if len(set(seen)) != len(seen):
        raise InputError("lie.agent", "one lie per agent")
    return tuple(out)


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--lie", action="append", type=_lie_arg, metavar="agent=ID,kind=K,size=X[,...]",
                        help="make an agent lie (repeat for several): kind offset|drift|shrink|stale|input, "
                        "size, and optionally from, until, on, off, scale, reports=honest|lying, withhold=TICK "
                        "(docs/faults.md); "
                        "replaces the scenario's [[faults.lies]]")


def _lie_arg(text: str) -> Lie:
    try:
        return parse_text(text)
    except InputError as e:
        raise argparse.ArgumentTypeError(f"{e.field}: {e.message}") from None


def to_argv(lies) -> list:
    """Command-line flags that give these lies (for children)."""
    out = []
    for lie in lies:
        out += ["--lie", lie.to_text()]
    return out


# --------------------------------------------------------------------------
# applying them
# --------------------------------------------------------------------------
class Liars:
    """The lies of a run on the sending side. ``lies``: resolved ``Lie``s;
    ``agents``: the run's ids along the last batch axis of the messages this
    object will see (all of them in the engine, one in an agent process);
    ``position_dims``: the state's position axes, along whose diagonal an
    estimate is moved. Keeps what a stale lie replays."""

    def __init__(self, lies, agents, n: int, position_dims=None):
        agents = list(agents)
        self.lies = [(agents.index(lie.agent), lie) for lie in lies if lie.agent in agents]
        dims = list(position_dims) if position_dims else list(range(n))
        self.direction = np.zeros(n)
        self.direction[dims] = 1.0 / math.sqrt(len(dims))
        self.keep = max([int(lie.size) for _, lie in self.lies if lie.kind == "stale"], default=0)
        self._sent: dict = {}     # k -> {column: Message} the liars' true messages (stale lies)
        self._reported: dict = {}  # k -> {column: Output}

    def __bool__(self) -> bool:
        return bool(self.lies)

    def message(self, k: int, msg: Message) -> Message:
        """What the agents send at tick ``k``: ``msg`` (their true messages,
        batch axes (..., N)) with each liar's column replaced by its lie."""
        if not self.lies:
            return msg
        self._remember(self._sent, k, msg)
        out = msg
        for col, lie in self.lies:
            if not lie.lying(k):
                continue
            true = msg.take(_column(msg.d_valid, col))
            if lie.kind == "stale":
                told = self._past(self._sent, k - int(lie.size), col)
            elif lie.kind == "input":
                told = replace(true, d=np.full_like(true.d, lie.size), d_valid=np.ones_like(true.d_valid))
            else:
                shift = lie.shift(k) * self.direction
                told = replace(true, x_pred=true.x_pred + shift, x_upd=true.x_upd + shift)
                if lie.kind == "shrink":
                    told = replace(told, P_pred=lie.scale * true.P_pred, P_upd=lie.scale * true.P_upd)
            out = _put(out, col, told)
        return out

    def withholds(self, k: int) -> bool:
        """Whether a liar here sends no report of tick ``k``."""
        return any(lie.withhold == k for _, lie in self.lies)

    def report(self, k: int, out: Output) -> Output:
        """What the agents report at tick ``k``: ``out`` with each liar whose
        reports lie (``reports = "lying"``) reporting the lie of its message."""
        if not any(lie.reports == "lying" for _, lie in self.lies):
            return out
        self._remember(self._reported, k, out)
        result = out
        for col, lie in self.lies:
            if lie.reports != "lying" or not lie.lying(k):
                continue
            true = _take_output(out, col)
            if lie.kind == "stale":
                told = self._past(self._reported, k - int(lie.size), col)
            elif lie.kind == "input":
                told = Output(true.x, true.P, np.full_like(true.d, lie.size), np.ones_like(true.d_valid))
            else:
                x = true.x + lie.shift(k) * self.direction
                P = lie.scale * true.P if lie.kind == "shrink" else true.P
                told = Output(x, P, true.d, true.d_valid)
            result = _put_output(result, col, told)
        return result

    def _remember(self, store: dict, k: int, value) -> None:
        if not self.keep:
            return
        take = ((lambda c: value.take(_column(value.d_valid, c))) if isinstance(value, Message)
                else (lambda c: _take_output(value, c)))
        store[k] = {col: take(col) for col, lie in self.lies if lie.kind == "stale"}
        for old in [t for t in store if t < k - self.keep]:
            del store[old]

    @staticmethod
    def _past(store: dict, k: int, col: int):
        """The true value of tick ``k`` (the oldest kept while there is none that old)."""
        return store[max(k, min(store))][col]


def _column(valid: np.ndarray, col: int) -> tuple:
    """The index of column ``col`` of the last batch axis (``valid`` has the batch axes only)."""
    return (slice(None),) * (valid.ndim - 1) + (col,)


def _put(msg: Message, col: int, told: Message) -> Message:
    """``msg`` with column ``col`` of its last batch axis replaced by ``told``."""
    index = _column(msg.d_valid, col)
    changed = {}
    for f in fields(Message):
        a = getattr(msg, f.name).copy()
        a[index] = getattr(told, f.name)
        changed[f.name] = a
    return Message(**changed)


def _take_output(out: Output, col: int) -> Output:
    index = _column(out.d_valid, col)
    return Output(out.x[index], out.P[index], out.d[index], out.d_valid[index])


def _put_output(out: Output, col: int, told: Output) -> Output:
    index = _column(out.d_valid, col)
    x, P, d, v = out.x.copy(), out.P.copy(), out.d.copy(), out.d_valid.copy()
    x[index], P[index], d[index], v[index] = told.x, told.P, told.d, told.d_valid
    return Output(x, P, d, v)
