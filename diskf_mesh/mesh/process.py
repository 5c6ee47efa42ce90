"""The skeleton of a mesh process, and one tick through the mesh in the order the code runs it.

The world's protocol is a state machine with no I/O
(``mesh.world_machine.WorldMachine``), run by the generic ``mesh.shell.Shell``
(the same lock, callbacks and main thread as below, for any machine). An
agent (``agents.agent.Agent``) is a ``Process``:

    one lock      the protocol state sits behind ``_cv`` (a condition on a
                  re-entrant lock: a put may deliver to this process on the
                  same thread)
    callbacks     the transport calls ``_on_sample(key, payload)`` on its
                  own thread (zenoh's network thread) for every sample and
                  every liveliness change (``payload`` True or False); it
                  takes the lock and hands the sample to the subclass's
                  ``_take_in``, which takes every step the new state allows
                  right there, with no hop to another thread
    failures      whatever a callback raises is kept (``_fail``: the first
                  one) and raised by the main thread (``_raise_failure``)
    the main      thread only starts the process, waits (``_wait``: at most
                  ``POLL_S`` at a time; waking more than ``FREEZE_S`` late
                  means the process was frozen, ``_woke``; ``_wait_until``),
                  watches the deadlines and the stop, and claims the
                  process's id (``_other_nonces``: a liveliness query for
                  another process holding it)

One tick k through the mesh (lockstep; real time differs only in who closes
a tick, ``mesh.clock``):

 1. world      ``WorldMachine._open_tick(k)``: each live agent's measurement
               (``wire.encode_measurement``, on the agent's own key, not
               express) and then the tick (``wire.encode_tick``: every
               position and the live set), published.
 2. agent      ``Agent._take_in``: the key is parsed once (``Keys.parse``:
               kind and agent id), the payload decoded once
               (``wire.decode_measurement``, ``wire.decode_tick``) and taken
               if it fits the run (``_meas_problem``, ``_tick_problem``). The
               tick gives the agents linked at k (live, in range:
               ``Agent.linked``) and lets through the neighbours' messages
               of k that came before it (``Receiver.release``).
 3. agent      ``Agent._open(k)``: the local step (``AgentEstimator.local``),
               its one message encoded (``wire.encode``: the fields its
               estimator exchanges, ``Estimator.exchanged``) and published
               on a key addressed to the linked agents.
 4. neighbour  ``Agent._take_in`` -> ``Receiver.on_payload(sender, payload)``
               with the sender the key named: ``Guard.screen`` decodes the
               payload once (``wire.decode``: schema, finite, positive
               definite) and checks the same floats once (the tick window,
               magnitude, conditioning, information: ``guard``); the range
               gate drops a sender not linked at the message's tick; the
               link's faults (``FaultModel.plan``, delayed copies in the
               ``DelayLine``, the simulated network); the message then waits
               in one place, the ``Inbox``, until its tick is fused (one
               whose tick the world has not opened at this agent yet waits
               for that, before its link: ``Receiver.release``).
 5. neighbour  ``Agent._close(k)`` once every linked sender is accounted for
               (arrived, lost, rejected) or the collection ends:
               ``Receiver.take`` -> ``AgentEstimator.fuse`` ->
               ``wire.encode_report`` (the fused estimate, the counters, what
               was fused and why the rest was not) on its report key.
 6. world      ``Shell`` -> ``WorldMachine.handle(Sample)`` -> ``_on_report``
               (``wire.decode_report``) -> ``_take`` records it; the last
               report of tick k closes it (``_advance`` -> ``_close_tick``)
               and opens tick k + 1 (``_open_tick``, step 1): the machine
               returns the ``Publish`` effects and the shell puts them, in
               the same callback.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import math
import threading
import time

from diskf_mesh.mesh.keys import Keys, new_nonce, nonce
from diskf_mesh.mesh.log import Log
from diskf_mesh.mesh.profile import NO_PHASES, Phases
from diskf_mesh.mesh.transport import Transport

POLL_S = 0.5    # the main thread looks at its deadlines at least this often
FREEZE_S = 2.0  # the main thread this late: the process was not running (SIGSTOP, or starved)
CLAIM_S = 1.0   # the liveliness query for another process holding this one's id


class Process:
    """One mesh process over a ``Transport``: the lock, the callback, the
    failure, the main thread's wait (module docstring). A subclass
    implements ``_take_in`` (lock held) and may override ``_woke``."""

    def __init__(self, keys: Keys, transport: Transport, log: Log, profile: Phases = NO_PHASES):
        self.keys = keys
        self.transport = transport
        self.log = log
        self.prof = profile
        self.nonce = new_nonce()  # this process's tokens end in it (mesh.keys)
        self.failure: BaseException | None = None  # raised in a callback, re-raised by the main thread
        self._cv = threading.Condition(threading.RLock())  # the protocol state, shared with the callbacks
        self._main_looks_at = math.inf  # when the main thread looks at its deadlines next (inf: awake)

    # -- the transport's callback ------------------------------------------
    def _on_sample(self, key: str | None, payload) -> None:
        """Every sample and every liveliness change (``payload`` True or
        False), on the transport's thread; ``key`` None: only look whether a
        step can be taken (e.g. a delayed copy came)."""
        self.prof.begin()
        try:
            with self._cv:
                self._take_in(key, payload)
        except BaseException as e:  # noqa: BLE001 - a callback must not swallow a failure
            self._fail(e)
        finally:
            self.prof.end("other")

    def _take_in(self, key: str | None, payload) -> None:  # pragma: no cover - abstract
        """Lock held: take in one sample and every step it allows."""
        raise NotImplementedError

    def _fail(self, e: BaseException) -> None:
        with self._cv:
            if self.failure is None:
                self.failure = e
            self._cv.notify_all()

    def _raise_failure(self) -> None:
        if self.failure is not None:
            raise self.failure

    # -- the main thread ----------------------------------------------------
    def _wait(self, until: float) -> None:
        """Main thread, lock held: sleep until notified or ``until``, at most
        ``POLL_S``; then ``_woke`` with how late it woke."""
        now = time.monotonic()
        timeout = max(min(until, now + POLL_S), now) - now
        self._main_looks_at = now + timeout
        self._cv.wait(timeout)
        late = time.monotonic() - self._main_looks_at
        self._main_looks_at = math.inf  # awake: a callback cannot tell a freeze from work
        self._woke(late)

    def _woke(self, late: float) -> None:
        """After a wait, ``late`` seconds after the planned wake-up (more than
        ``FREEZE_S``: the process was frozen). Default: nothing."""

    def _wait_until(self, done, until: float, check=None) -> bool:
        """Main thread, lock held: wait until ``done()``, sleeping at most to
        the monotonic ``until`` at a time. Without ``check``, the wait ends at
        ``until`` (returns ``done()``); with it, ``check()`` before every wait
        ends it (it raises, e.g. past ``until``)."""
        while not done():
            if check is not None:
                check()
            elif time.monotonic() >= until:
                return False
            self._wait(until)
        return True

    def _other_nonces(self, key_expr: str) -> set:
        """Main thread, lock not held: the nonces of the tokens on
        ``key_expr`` that the network holds now, this process's excepted."""
        return {nonce(k) for k in self.transport.tokens(key_expr, CLAIM_S)} - {self.nonce}
