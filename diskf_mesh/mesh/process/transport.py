"""The transport: the only place a mesh process touches the network.

A ``Transport`` publishes bytes on a key, delivers the samples of a key
expression to a callback, declares liveliness tokens and reports tokens
appearing and going, and carries queries (a process answers the queries on
a key expression; another asks one and gets the first answer, or none). ``ZenohTransport`` is the one a mesh process runs; the
tests' ``local_bus.LocalBus`` hands samples between threads of one process.

Callbacks run on the transport's own threads (zenoh's network thread),
never inside the publisher's ``put``: a mesh
process does its per-message work right there, under its own lock, and wakes
its main thread only for what that thread does (start-up, timeouts, the
end). Link faults are not here: they act in each agent's receive path
(``diskf_mesh.mesh.protocol.receive``), on the messages this layer delivered.
"""
from __future__ import annotations

import collections
import ctypes
import os
import threading
import time
from typing import Callable


OnSample = Callable[[str, bytes], None]
OnToken = Callable[[str, bool], None]
OnQuery = Callable[[str, bytes, Callable[[bytes], None]], None]  # (key, payload, reply)
OnReply = Callable[[bytes | None], None]


ZENOH_RUNTIME = "(rx: (worker_threads: 1))"
BATCHING = "transport/link/tx/queue/batching"
# tests only: a file an agent process waits for before declaring its alive token (a process
# descheduled between its claim's query and its declaration, as on a loaded machine)
ALIVE_GATE_ENV = "DISKF_MESH_TEST_ALIVE_GATE"
PUBLISHERS_KEPT = 64  # declared publishers kept per session (one per key)


class MeshError(RuntimeError):
    """The run cannot go on (a timeout, a peer gone, a mismatch); the command
    prints ``error: <message>`` and exits with status ``status`` (1)."""

    status = 1


class DuplicateProcess(MeshError):
    """Another process holds this process's id (an agent id, or the world of
    the run id): this one leaves, exit status 2."""

    status = 2


class Transport:
    """Interface; see the module docstring."""

    def put(self, key: str, payload: bytes, express: bool = True) -> None:  # pragma: no cover - interface
        """Publish ``payload`` on ``key``. ``express=False``: it may wait in
        its link's batch (at most ``ZenohTransport``'s ``hold_ms``) for the
        next express message on the same link, and both go in one write."""
        raise NotImplementedError

    def subscribe(self, key_expr: str, on_sample: OnSample) -> None:  # pragma: no cover
        raise NotImplementedError

    def declare_token(self, key: str):  # pragma: no cover
        """Declare a liveliness token; returns it (``undeclare()`` withdraws it)."""
        raise NotImplementedError

    def tokens(self, key_expr: str, timeout: float = 1.0) -> list:  # pragma: no cover
        """The keys of the tokens matching ``key_expr`` that the network holds
        now (a liveliness query, waiting at most ``timeout`` seconds)."""
        raise NotImplementedError

    def watch_tokens(self, key_expr: str, on_change: OnToken) -> None:  # pragma: no cover
        """``on_change(key, alive)`` for tokens matching ``key_expr``, those
        already declared included."""
        raise NotImplementedError

    def declare_queryable(self, key_expr: str, on_query: OnQuery) -> None:  # pragma: no cover
        """``on_query(key, payload, reply)`` for every query on ``key_expr``;
        ``reply(payload)`` answers it, once, at any time later (or never:
        the asker's timeout)."""
        raise NotImplementedError

    def query(self, key: str, payload: bytes, timeout: float, on_reply: OnReply) -> None:  # pragma: no cover
        """Ask the queryables of ``key``; ``on_reply(payload)`` once, with the
        first answer, or ``on_reply(None)`` if none came within ``timeout``
        seconds. Returns at once."""
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# --------------------------------------------------------------------------
# zenoh
# --------------------------------------------------------------------------
class ZenohTransport(Transport):
    """One zenoh session. Publishers are declared once per key, reliable,
    blocking on congestion (a fault-free run loses nothing), express (sent
    at once, not batched: a tick is latency bound) unless the key's first put
    says otherwise, and for other sessions only (a process does not hear its
    own messages: zenoh would call its subscriber inside ``put``)."""

    def __init__(self, options, hold_ms: int | None = None):
        """``hold_ms``: how long a non-express message may wait in its link's
        batch for company (zenoh's batching time limit), unless ``options``
        set it."""
        import zenoh

        # one thread reads every link (zenoh's "rx" runtime; its default is two
        # here): the callbacks of a process then never take the GIL from each
        # other, which measured 10-15 % more ticks per second on two cores.
        # Read once, when the first session opens; a ZENOH_RUNTIME of the
        # user's wins.
        os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
        self._zenoh = zenoh
        zenoh.init_log_from_env_or("error")
        conf = options.to_config()
        if hold_ms is not None and not options.config_file and not any(c.startswith(BATCHING) for c in options.cfg):
            conf.insert_json5(f"{BATCHING}/time_limit", str(int(hold_ms)))
        try:
            self._session = zenoh.open(conf)
        except zenoh.ZError as e:
            raise MeshError(f"cannot open a zenoh session: {e}") from None
        self._publishers = collections.OrderedDict()  # key -> publisher, least recently used first
        self._entities = []
        self._kept = set()  # ids of zenoh's threads whose Python thread state is kept (``keep_thread_state``)

    def put(self, key, payload, express=True):
        pub = self._publishers.get(key)
        if pub is None:  # a key's first put decides whether it is express
            pub = self._session.declare_publisher(
                key, congestion_control=self._zenoh.CongestionControl.BLOCK, express=express,
                allowed_destination=self._zenoh.Locality.REMOTE)
            self._publishers[key] = pub
            if len(self._publishers) > PUBLISHERS_KEPT:  # addressed keys come and go with the links
                self._publishers.popitem(last=False)[1].undeclare()
        else:
            self._publishers.move_to_end(key)
        pub.put(payload)

    def _direct(self, fn, drop=None):
        """``direct_callback`` of ``fn`` (and ``drop``) for this transport."""
        return direct_callback(self._zenoh, fn, self._kept, drop)

    def subscribe(self, key_expr, on_sample):
        def cb(sample):
            on_sample(str(sample.key_expr), sample.payload.to_bytes())

        self._entities.append(self._session.declare_subscriber(key_expr, self._direct(cb)))

    def declare_token(self, key):
        gate = os.environ.get(ALIVE_GATE_ENV) if "/alive/agent/" in key else None
        if gate:  # a test's slow process: held until the test opens the gate (at most 120 s)
            stop = time.monotonic() + 120.0
            while not os.path.exists(gate) and time.monotonic() < stop:
                threading.Event().wait(0.01)
        token = self._session.liveliness().declare_token(key)
        self._entities.append(token)
        return token

    def tokens(self, key_expr, timeout=1.0):
        replies = self._session.liveliness().get(key_expr, timeout=timeout)
        return sorted({str(r.ok.key_expr) for r in replies if r.ok is not None})

    def watch_tokens(self, key_expr, on_change):
        put = self._zenoh.SampleKind.PUT

        def cb(sample):
            on_change(str(sample.key_expr), sample.kind == put)

        self._entities.append(self._session.liveliness().declare_subscriber(key_expr, self._direct(cb), history=True))

    def declare_queryable(self, key_expr, on_query):
        def cb(query):
            key = str(query.key_expr)

            def reply(payload):
                try:
                    query.reply(key, payload)
                finally:
                    query.drop()  # answered: the asker need not wait for its timeout

            on_query(key, b"" if query.payload is None else query.payload.to_bytes(), reply)

        self._entities.append(self._session.declare_queryable(key_expr, self._direct(cb)))

    def query(self, key, payload, timeout, on_reply):
        once = _Once(on_reply)

        def cb(reply):
            if reply.ok is not None:
                once(reply.ok.payload.to_bytes())

        self._session.get(key, self._direct(cb, lambda: once(None)), payload=payload, timeout=timeout)

    def close(self):
        if self._session.is_closed():
            return
        for e in self._entities + list(self._publishers.values()):
            try:
                e.undeclare()
            except Exception:  # already gone with the session: nothing to release
                pass
        self._session.close()


def direct_callback(zenoh, fn, kept: set, drop=None):
    """A zenoh callback that runs ``fn`` on zenoh's own network thread, not
    on an extra Python thread per subscriber: one thread hop less per
    sample, which is most of a small message's cost. A callback may ``put``
    (never to its own process: a publisher reaches the other processes only). Each
    thread's Python state is kept from callback to callback
    (``keep_thread_state``; ``kept``: the threads kept so far)."""
    def run(arg):
        keep_thread_state(kept)
        fn(arg)
    return zenoh.handlers.Callback(run, drop, indirect=False)


def keep_thread_state(kept: set) -> None:
    """Keep the Python thread state of the thread running this (a zenoh
    thread, in a callback) for its next call into Python. Zenoh's threads
    are not Python's: each call into Python makes a thread state and
    deletes it on return (``PyGILState_Ensure`` and ``Release``), so every
    sample paid for a new one and its frame stack (fresh memory: most of a
    mesh process's page faults). One ``Ensure`` more, never released, keeps
    it; the GIL is held here, so it only counts. ``kept``: the ids of the
    threads already kept (one ``Ensure`` each)."""
    ident = threading.get_ident()
    if ident not in kept:
        kept.add(ident)
        ctypes.pythonapi.PyGILState_Ensure()


class _Once:
    """A query's ``on_reply``, called at most once (the first answer, or
    None when the query ends without one)."""

    def __init__(self, on_reply: OnReply):
        self._on_reply, self._lock, self._done = on_reply, threading.Lock(), False

    def __call__(self, payload) -> bool:
        with self._lock:
            if self._done:
                return False
            self._done = True
        self._on_reply(payload)
        return True
