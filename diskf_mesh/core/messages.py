"""What agents exchange: one message per agent per tick.

``Message`` holds the published quantities of Algorithm 1, step 2, as arrays
with leading batch axes (seeds x agents in the engine; one agent in a
process). It never holds a raw measurement, an H or an R. The wire format
(schema version, sender id, tick) lives in ``diskf_mesh.mesh.wire.codec``.

Fields (tick k):
    x_pred, P_pred  x^_{k|k-1}, P^_{k|k-1}   prediction (without input)
    x_upd,  P_upd   x~_{k|k},   P~_{k|k}     after the sender's own update
    d, S            the sender's input estimate of d_{k-1} entering fusion and
                    its covariance (Algorithm 1 labels them d_bar, S_bar)
    d_valid         whether d, S are an estimate at all (window, rank)
    w               the sender's probabilities of its input models (``diskf-auto``);
                    (..., 0) for an estimator with one input model
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Message:
    x_pred: np.ndarray
    P_pred: np.ndarray
    x_upd: np.ndarray
    P_upd: np.ndarray
    d: np.ndarray
    S: np.ndarray
    d_valid: np.ndarray
    w: np.ndarray | None = None  # None: no model probabilities, an empty (..., 0) array

    ARRAY_FIELDS = ("x_pred", "P_pred", "x_upd", "P_upd", "d", "S", "w")

    def __post_init__(self):
        if self.w is None:
            object.__setattr__(self, "w", np.zeros(np.shape(self.d_valid) + (0,)))

    def take(self, index) -> "Message":
        """Select along the leading axes, e.g. one agent out of a batch."""
        return Message(*(getattr(self, name)[index] for name in _MESSAGE_FIELDS))

    @classmethod
    def stack(cls, msgs, axis: int = 0) -> "Message":
        """Messages of equal shapes stacked along a new ``axis``."""
        if axis == 0:  # np.array of equal-shape arrays: the same array as np.stack, 4x faster on small ones
            return cls(*(np.array([getattr(m, name) for m in msgs]) for name in _MESSAGE_FIELDS))
        return cls(*(np.stack([getattr(m, name) for m in msgs], axis=axis) for name in _MESSAGE_FIELDS))


_MESSAGE_FIELDS = tuple(f.name for f in fields(Message))


@dataclass(frozen=True)
class Neighbourhood:
    """Who a receiver fuses at one tick.

    adj:       (..., R, S) 1.0 where receiver r fuses sender s (itself included)
    self_mask: (..., R, S) True where sender s is receiver r
    draws:     (..., R) the estimator's draw of each receiver at this tick
               (``Estimator.draws``, e.g. GDKF's gossip), None if it has none
    columns:   (..., R, S) each sender's place among the run's agents (the
               scenario's order), None where sender s is agent s
    """

    adj: np.ndarray
    self_mask: np.ndarray
    draws: np.ndarray | None = None
    columns: np.ndarray | None = None

    @cached_property
    def n_neighbours(self) -> np.ndarray:
        """(..., R) how many senders each receiver fuses besides itself
        (|N_i| of the compensation gain), computed once per neighbourhood."""
        return self.adj.sum(axis=-1) - (self.adj * self.self_mask).sum(axis=-1)

    @cached_property
    def linked(self) -> np.ndarray:
        """(..., R, S) the senders each receiver fuses besides itself."""
        return (self.adj > 0) & ~self.self_mask

    @cached_property
    def linked_pairs(self) -> tuple:
        """``core.resilience.linked_pairs`` of ``linked``, computed once per
        neighbourhood."""
        from diskf_mesh.core.resilience import linked_pairs

        return linked_pairs(self.linked)


@dataclass(frozen=True)
class Output:
    """What an agent reports after fusion at tick k."""

    x: np.ndarray
    P: np.ndarray
    d: np.ndarray
    d_valid: np.ndarray
