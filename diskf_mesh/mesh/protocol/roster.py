"""Which agents of a run an agent process sees alive: its view of the
agents' alive tokens (``keys.alive``).

An agent needs of the others' tokens only whether every agent of the
scenario holds one (start-up), whether some do (a rejoin waits for its
peers) and who else holds its own id (a duplicate). ``Roster`` keeps a count
of tokens per id (one per process holding it; a shell reports a token's
coming and going once each) in one small array, and the nonces of the
processes holding its own id, so what it holds per peer is two bytes; a
batch of tokens (``events.TokenBatch``) is counted in one call.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import numpy as np

from diskf_mesh.mesh.wire.keys import Keys, nonce as nonce_of


class Roster:
    def __init__(self, ids: tuple, places: dict, own: int):
        """``ids``: the scenario's agent ids; ``places``: id -> its place in
        ``ids`` (``Scenario.index``'s map, shared by the run's machines)."""
        self._places, self.own = places, own
        self._held = np.zeros(len(ids), np.int16)
        self.size = 0             # ids with a token
        self.mine = ()            # nonces of the processes holding ``own`` (this one's included)

    def __contains__(self, who) -> bool:
        i = self._places.get(who)
        return i is not None and bool(self._held[i])

    @property
    def complete(self) -> bool:
        """Every id of the scenario holds a token."""
        return self.size == len(self._held)

    def has(self, ids) -> bool:
        return all(who in self for who in ids)

    def token(self, who, nonce: str, up: bool) -> None:
        """One token of agent ``who`` (process ``nonce``) came or went."""
        i = self._places[who]
        if who == self.own:
            self.mine = tuple(n for n in self.mine if n != nonce) + ((nonce,) if up else ())
            count = len(self.mine)
        else:
            count = max(0, int(self._held[i]) + (1 if up else -1))
        self.size += bool(count) - bool(self._held[i])
        self._held[i] = count

    def tokens(self, places: np.ndarray, up: bool) -> None:
        """Tokens of agents other than ``own`` (``places``: their places in
        ``ids``, one per token) came or went."""
        if not len(places):
            return
        if up:
            np.add.at(self._held, places, 1)
        else:
            np.subtract.at(self._held, places, 1)
            np.maximum(self._held, 0, out=self._held)
        self.size = int(np.count_nonzero(self._held))


def parse_batch(keys: Keys, places: dict, batch: tuple) -> tuple:
    """(places, nonces, others) of a batch of token keys: the places in the
    scenario's ids of its agents' alive tokens, their nonces (in the same
    order), and every other key (the world's, foreign ones), in order."""
    at, nonces, others = [], [], []
    for key in batch:
        kind, who = keys.parse(key)
        i = places.get(who) if kind == "alive" else None
        if i is None:
            others.append(key)
        else:
            at.append(i)
            nonces.append(nonce_of(key))
    return np.asarray(at, np.intp), tuple(nonces), tuple(others)
