"""Seeded per-link network faults: loss, latency with jitter, duplication, reordering.

The fault model is pure logic. ``FaultModel.plan(sender, receiver, tick)``
says what the link from ``sender`` to ``receiver`` does with the sender's
message of ``tick``: nothing arrives (lost), or one or two copies arrive, each
after its own delay. A transport applies the plan on the receiving side
(``diskf_mesh.mesh.protocol.delayline`` holds delayed copies until they are due), so the
estimation code never sees a fault, only what arrived.

Every decision is drawn from a numpy ``Generator`` seeded by
(run seed, sender, receiver): the link's stream is cut into one fixed-size
row of uniform draws per tick, so a decision depends only on
(seed, sender, receiver, tick), not on which other messages were sent or in
what order they were processed. The same seed gives the same faults.

Per message on a link (probabilities and times from ``FaultConfig``):

    lost        with probability ``loss``: no copy arrives
    delay       latency_ms + jitter_ms * (2u - 1), clipped at 0: uniform in
                [latency - jitter, latency + jitter]
    duplicate   with probability ``duplicate`` a second copy arrives, with its
                own delay
    reorder     with probability ``reorder`` (per copy) the copy is held back
                ``reorder_ms`` longer, so messages sent after it on the link
                overtake it. In a lockstep run the next message on a link comes
                a tick later, so a reordered copy usually misses its tick and
                is counted late: the estimator fuses only what arrived in time.

A scenario file sets them in a ``[faults]`` table with these names; the
command line (``--loss 0.2 --latency-ms 5 --jitter-ms 5 --duplicate 0.05
--reorder 0.05 --reorder-ms 50``) overrides the file field by field.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from diskf_mesh.core.errors import InputError
from diskf_mesh.data.argtypes import MAX_MS, fraction, milliseconds

PROBABILITIES = ("loss", "duplicate", "reorder")
DURATIONS = ("latency_ms", "jitter_ms", "reorder_ms")
FAULT_STREAM = 0xFA17  # keeps the fault streams apart from every other seeded stream
_CHUNK = 64            # ticks of draws generated at a time per link
# one row of uniforms per (link, tick): loss, copy 1 delay, copy 1 reorder,
# duplicate, copy 2 delay, copy 2 reorder
_U_LOSS, _U_DELAY1, _U_REORDER1, _U_DUP, _U_DELAY2, _U_REORDER2 = range(6)
_ROW = 6


@dataclass(frozen=True)
class FaultConfig:
    """What every link of a run does to messages. All zero: a perfect network."""

    loss: float = 0.0
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_ms: float = 50.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise InputError(f.name, f"must be a finite non-negative number, got {v!r}")
            if f.name in PROBABILITIES and v > 1:
                raise InputError(f.name, f"is a probability, must be at most 1, got {v!r}")
            if f.name in DURATIONS and v > MAX_MS:
                raise InputError(f.name, f"must be at most {MAX_MS:.0f} ms (a day), got {v!r}")

    @property
    def active(self) -> bool:
        """Whether any message can be lost, delayed, duplicated or reordered."""
        return any((self.loss, self.latency_ms, self.jitter_ms, self.duplicate, self.reorder))

    @classmethod
    def from_mapping(cls, table: dict, where: str = "faults") -> "FaultConfig":
        """From a scenario's ``[faults]`` table; unknown names are an error."""
        if not isinstance(table, dict):
            raise InputError(where, "must be a table")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(table) - known)
        if unknown:
            raise InputError(f"{where}.{unknown[0]}", f"unknown fault setting; known: {', '.join(sorted(known))}")
        try:
            return cls(**table)
        except InputError as e:
            raise InputError(f"{where}.{e.field}", e.message) from None

    def with_overrides(self, **given) -> "FaultConfig":
        """This configuration with the given fields replaced (None: keep)."""
        return replace(self, **{k: v for k, v in given.items() if v is not None})

    def to_dict(self) -> dict:
        return asdict(self)

    def to_argv(self) -> list:
        """Command-line flags that reproduce this configuration (for children)."""
        out = []
        for f in fields(self):
            out += [_flag(f.name), repr(float(getattr(self, f.name)))]
        return out


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The fault flags; each overrides the scenario's ``[faults]`` entry."""
    g = parser.add_argument_group("network faults (per link, seeded; override the scenario's [faults])")
    g.add_argument("--loss", type=fraction, metavar="P", help="probability that a message is lost")
    g.add_argument("--latency-ms", type=milliseconds, metavar="MS", help="fixed link latency")
    g.add_argument("--jitter-ms", type=milliseconds, metavar="MS", help="latency varies uniformly by +-MS")
    g.add_argument("--duplicate", type=fraction, metavar="P", help="probability of a second copy")
    g.add_argument("--reorder", type=fraction, metavar="P", help="probability that a copy is held back")
    g.add_argument("--reorder-ms", type=milliseconds, metavar="MS",
                   help="how long a reordered copy is held back (default 50)")


def from_args(args: argparse.Namespace, scenario_faults: dict | None = None) -> FaultConfig:
    """The scenario's ``[faults]`` table with the flags the user gave on top."""
    base = FaultConfig.from_mapping(scenario_faults or {})
    return base.with_overrides(**{f.name: getattr(args, f.name, None) for f in fields(FaultConfig)})


# --------------------------------------------------------------------------
# the model
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class Delivery:
    """One copy of a message arriving ``delay_s`` seconds after it was sent."""

    delay_s: float
    copy: int = 0          # 0 the original, 1 the duplicate
    reordered: bool = False


PERFECT = (Delivery(0.0),)


class FaultModel:
    """Per-link fault decisions of one run. Holds one seeded stream per link."""

    def __init__(self, config: FaultConfig, seed: int):
        self.config = config
        self.seed = int(seed)
        self._draws: dict = {}  # (sender, receiver) -> (Generator, array of rows)

    def link_rng(self, sender: int, receiver: int) -> np.random.Generator:
        """The stream of the link sender -> receiver (seeded, independent per link)."""
        return np.random.default_rng([self.seed, int(sender), int(receiver), FAULT_STREAM])

    def _row(self, sender: int, receiver: int, tick: int) -> np.ndarray:
        key = (int(sender), int(receiver))
        rng, rows = self._draws.get(key) or (self.link_rng(*key), np.empty((0, _ROW)))
        if tick >= len(rows):
            more = (tick - len(rows)) // _CHUNK + 1
            rows = np.concatenate([rows, rng.random((more * _CHUNK, _ROW))])
        self._draws[key] = (rng, rows)
        return rows[tick]

    def plan(self, sender: int, receiver: int, tick: int) -> tuple:
        """What the link does with ``sender``'s message of ``tick``:
        () when it is lost, else one or two ``Delivery``s."""
        c = self.config
        if not c.active:
            return PERFECT
        if tick < 0:
            raise ValueError(f"tick must be >= 0, got {tick}")
        u = self._row(sender, receiver, tick)
        if u[_U_LOSS] < c.loss:
            return ()
        out = [self._copy(u[_U_DELAY1], u[_U_REORDER1], 0)]
        if u[_U_DUP] < c.duplicate:
            out.append(self._copy(u[_U_DELAY2], u[_U_REORDER2], 1))
        return tuple(out)

    def _copy(self, u_delay: float, u_reorder: float, copy: int) -> Delivery:
        c = self.config
        ms = max(0.0, float(c.latency_ms + c.jitter_ms * (2.0 * u_delay - 1.0)))
        reordered = bool(u_reorder < c.reorder)
        if reordered:
            ms += c.reorder_ms
        return Delivery(ms / 1000.0, copy, reordered)


def delivered_links(links: np.ndarray, ids, config: FaultConfig, seed: int, deadline_s: float = math.inf,
                    first_tick: int = 1) -> np.ndarray:
    """The links of a run after the faults: ``links`` (K, N, N) bool,
    [tick - first_tick, receiver, sender], with every off-diagonal link kept only where
    ``FaultModel(config, seed)`` delivers the sender's message of that tick to
    the receiver within ``deadline_s`` (a copy with a smaller delay).

    This is what an agent process fuses when every copy that is due before
    its collection deadline arrives in time, so an in-process run on these
    links (``engine.run`` on ``trace.with_links``) is the mesh run under the
    same faults and seed; with latency 0 it is exact (tested)."""
    links = np.asarray(links, dtype=bool)
    model = FaultModel(config, seed)
    out = links.copy()
    K, N, _ = links.shape
    for t in range(K):
        for r in range(N):
            for s in range(N):
                if r != s and links[t, r, s]:
                    plan = model.plan(ids[s], ids[r], t + first_tick)
                    out[t, r, s] = any(d.delay_s < deadline_s for d in plan)
    return out
