"""An in-process stand-in for zenoh, for tests of the shell and the
protocol: ``LocalBus().transport()`` per node, each a ``Transport``."""
from __future__ import annotations

import collections
import threading

from diskf_mesh.mesh.wire.keys import key_matches
from diskf_mesh.mesh.process.transport import Transport, _Once

class LocalBus:
    """A zenoh stand-in inside one process: ``bus.transport()`` per node.

    As with zenoh, a sample is delivered on the receiving node's own thread
    (one per ``LocalTransport``), in the order it was put, never on the
    publisher's: a callback may publish without re-entering itself."""

    def __init__(self):
        self._lock = threading.RLock()
        self._subs = []      # (owner, expr, callback)
        self._watchers = []  # (owner, expr, callback)
        self._queryables = []  # (owner, expr, callback)
        self._tokens = {}    # key -> owner count

    def transport(self) -> "LocalTransport":
        return LocalTransport(self)


class _LocalToken:
    def __init__(self, owner, key):
        self._owner, self._key = owner, key

    def undeclare(self):
        self._owner._undeclare(self._key)


class LocalTransport(Transport):
    def __init__(self, bus: LocalBus):
        self._bus = bus
        self._tokens = []
        self._closed = False
        self._queue = collections.deque()
        self._ready = threading.Condition(threading.Lock())
        self._thread = threading.Thread(target=self._deliver, name="localbus", daemon=True)
        self._thread.start()

    def _post(self, callback, *args) -> None:
        with self._ready:
            if self._closed:
                return
            self._queue.append((callback, args))
            self._ready.notify()

    def _deliver(self) -> None:
        while True:
            with self._ready:
                while not self._queue and not self._closed:
                    self._ready.wait()
                if not self._queue:
                    return
                callback, args = self._queue.popleft()
            callback(*args)

    def put(self, key, payload, express=True):
        with self._bus._lock:
            targets = [(owner, cb) for owner, e, cb in self._bus._subs if key_matches(e, key)]
        for owner, cb in targets:
            owner._post(cb, key, bytes(payload))

    def subscribe(self, key_expr, on_sample):
        with self._bus._lock:
            self._bus._subs.append((self, key_expr, on_sample))

    def _token_event(self, key, alive):
        with self._bus._lock:
            targets = [(owner, cb) for owner, e, cb in self._bus._watchers if key_matches(e, key)]
        for owner, cb in targets:
            owner._post(cb, key, alive)

    def declare_token(self, key):
        with self._bus._lock:
            self._bus._tokens[key] = self._bus._tokens.get(key, 0) + 1
            self._tokens.append(key)
        self._token_event(key, True)
        return _LocalToken(self, key)

    def _undeclare(self, key):
        with self._bus._lock:
            if key not in self._tokens:
                return
            self._tokens.remove(key)
            self._bus._tokens[key] -= 1
            gone = not self._bus._tokens[key]
            if gone:
                del self._bus._tokens[key]
        if gone:
            self._token_event(key, False)

    def tokens(self, key_expr, timeout=1.0):
        with self._bus._lock:
            return sorted(k for k in self._bus._tokens if key_matches(key_expr, k))

    def watch_tokens(self, key_expr, on_change):
        with self._bus._lock:
            self._bus._watchers.append((self, key_expr, on_change))
            present = [k for k in self._bus._tokens if key_matches(key_expr, k)]
        for k in present:
            self._post(on_change, k, True)

    def declare_queryable(self, key_expr, on_query):
        with self._bus._lock:
            self._bus._queryables.append((self, key_expr, on_query))

    def query(self, key, payload, timeout, on_reply):
        """Each answer is delivered on this transport's thread; no answer
        within ``timeout`` (a timer thread) delivers None."""
        with self._bus._lock:
            targets = [(owner, cb) for owner, e, cb in self._bus._queryables if key_matches(e, key)]
        once = _Once(lambda p: self._post(on_reply, p))
        timer = threading.Timer(timeout, once, args=(None,))
        timer.daemon = True
        timer.start()
        for owner, cb in targets:
            owner._post(cb, key, bytes(payload), once)

    def close(self):
        if self._closed:
            return
        with self._bus._lock:
            self._bus._subs = [s for s in self._bus._subs if s[0] is not self]
            self._bus._queryables = [q for q in self._bus._queryables if q[0] is not self]
            self._bus._watchers = [w for w in self._bus._watchers if w[0] is not self]
            gone = []
            for k in self._tokens:
                self._bus._tokens[k] -= 1
                if not self._bus._tokens[k]:
                    del self._bus._tokens[k]
                    gone.append(k)
        for k in gone:
            self._token_event(k, False)
        with self._ready:
            self._closed = True
            self._ready.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(5.0)
