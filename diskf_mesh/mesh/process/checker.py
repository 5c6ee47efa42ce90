"""The world's check as the run goes, in a process of its own beside the world.

``CheckProcess`` has the interface of ``mesh.protocol.run_status.OnlineCheck``
that ``WorldMachine`` calls (``submit``, ``result``): ``submit(rec, k)``
sends tick k's reports (its rows of the record and its digests as raw
bytes, and the rejoins and starting states when the run has any:
``tick_bytes``) down a pipe to a child process, forked before the world's
credentials are read, that holds its own ``OnlineCheck`` (made by
``make()``, the same engine replay on the same trace) and runs it there;
``result(rec, k, wait)`` hands back its finding, None while it is not done
unless ``wait``. The findings, and the tick each counts from, are the same
as a check in the world's own thread (``WorldMachine._check_ticks``); what
changes is where the CPU goes: the world's thread hands the next tick's
reports over while the child replays the last one, and the child runs
``NICE`` steps below the world, so the agents, whose work holds up the tick,
go first on a busy machine and the replay fills the time the cores would
idle.

The child ignores SIGINT (a Ctrl-C reaches the world, which ends the run)
and ends when the pipe closes (the world ended, however it ended). An
exception in the child is raised in the world as ``CheckFailed`` with the
child's traceback.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import struct
import time
import traceback

import numpy as np

from diskf_mesh.mesh.protocol.world_machine import WorldRecord
from diskf_mesh.mesh.protocol.reports import RunReports

NICE = 5       # steps of niceness below the world (os.nice)
JOIN_S = 2.0   # at the end, for the child to leave before it is terminated
HEADER = struct.Struct("<qqq")    # a tick handed over: the tick, its digests, what it holds (``tick_bytes``)
ANSWER = struct.Struct("<bqd")    # the child's answer: its kind, the tick, the child's CPU seconds; then its body
READY, FOUND, ERROR = 0, 1, 2     # the kinds: the check is made; a tick's finding (pickled, none if empty); a traceback


class CheckFailed(RuntimeError):
    """The check's process failed (its traceback), or ended early."""


class CheckProcess:
    """``OnlineCheck``'s ``submit`` and ``result`` (module docstring) in a
    child process; ``make()`` makes its ``OnlineCheck`` there. ``cpu_s``:
    the child's CPU seconds so far (as of its latest finding)."""

    elsewhere = True  # the world hands each tick over when it is final, and asks for the finding later

    def __init__(self, make, nice: int = NICE):
        ctx = multiprocessing.get_context("fork")
        self._conn, theirs = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(make, theirs, self._conn, nice), daemon=True,
                                 name="online-check")
        self._proc.start()
        theirs.close()
        self._sent = 0      # the last tick sent
        self._found = {}    # tick -> finding, not asked for yet
        self.cpu_s = 0.0    # the child's CPU seconds, as of its latest message
        self._ready_cpu_s = None  # ... once its check was made (before the first tick)

    @property
    def ticking_cpu_s(self) -> float:
        """The child's CPU seconds since its check was made: the replay of
        the ticks it checked."""
        return self.cpu_s - (self._ready_cpu_s or 0.0)

    def submit(self, rec, k: int) -> None:
        """Tick k's reports are final: send them (once)."""
        if k <= self._sent:
            return
        try:
            self._conn.send_bytes(tick_bytes(rec, k))
        except OSError:  # a broken pipe: the child is gone
            raise self._ended(k) from None
        self._sent = k

    def result(self, rec, k: int, wait: bool = True) -> list | None:
        """Tick k's finding (``OnlineCheck.tick``), None if it is not in yet
        and not ``wait``."""
        self.submit(rec, k)
        while k not in self._found:
            if not wait and not self._conn.poll():
                return None
            try:
                data = self._conn.recv_bytes()
            except (EOFError, OSError):  # the child is gone
                raise self._ended(k) from None
            kind, tick, self.cpu_s = ANSWER.unpack_from(data)
            if kind == ERROR:
                raise _failed(tick, data)
            if kind == READY:
                self._ready_cpu_s = self.cpu_s
                continue
            self._found[tick] = pickle.loads(data[ANSWER.size:]) if len(data) > ANSWER.size else []
        return self._found.pop(k)

    def _ended(self, k: int) -> CheckFailed:
        """The child is gone: its error if it sent one before it ended
        (the pipe may break before the world reads it), else how it ended."""
        try:
            while self._conn.poll():
                data = self._conn.recv_bytes()
                if ANSWER.unpack_from(data)[0] == ERROR:
                    return _failed(ANSWER.unpack_from(data)[1], data)
        except (EOFError, OSError):
            pass
        self._proc.join(JOIN_S)
        return CheckFailed(f"the online check's process ended (exit status {self._proc.exitcode}) before tick {k} "
                           "was checked")

    def close(self) -> None:
        """End the child: close the pipe, wait ``JOIN_S`` for it to leave."""
        self._conn.close()
        self._proc.join(JOIN_S)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join()


def _serve(make, conn, other, nice: int) -> None:
    """The child: check each tick sent, in order, until the pipe closes."""
    other.close()  # the world's end: when the world closes its own, recv ends here
    null = os.open(os.devnull, os.O_RDONLY)  # the world's standard input, where its identity comes: not ours
    os.dup2(null, 0)
    os.close(null)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.nice(nice)
    try:
        _check_each(make, conn)
    except (EOFError, ConnectionError):  # the world closed its end, with what it had not read yet: it ended
        return


def _failed(k: int, data: bytes) -> CheckFailed:
    """The child's ``ERROR`` answer about tick k as the world raises it."""
    return CheckFailed(f"the online check failed at tick {k}:\n{data[ANSWER.size:].decode()}")


def _answer(conn, kind: int, k: int, body: bytes = b"") -> None:
    conn.send_bytes(ANSWER.pack(kind, k, time.process_time()) + body)


def _check_each(make, conn) -> None:
    """Make the check, then check each tick as it comes; the pipe's end
    raises (``EOFError``, ``ConnectionError``)."""
    try:
        check = make()
    except Exception:  # noqa: BLE001 - the world raises it when it asks (its own setup fails the same way first)
        _answer(conn, ERROR, 0, traceback.format_exc().encode())
        return
    _answer(conn, READY, 0)
    B, K, N = check.trace.has.shape
    rec = WorldRecord(**RunReports.empty(K, N, check.trace.model.n, check.trace.model.m),
                      live=np.zeros((K, N), dtype=bool))
    while True:
        k, said = read_tick(conn.recv_bytes(), rec)
        try:
            found = check.tick(rec, k, said)
        except Exception:  # noqa: BLE001 - the world raises it
            _answer(conn, ERROR, k, traceback.format_exc().encode())
            return
        _answer(conn, FOUND, k, pickle.dumps(found) if found else b"")


def tick_bytes(rec, k: int) -> bytes:
    """Tick k of the world's record ``rec`` as the check's process reads it
    (``read_tick``): ``HEADER`` (the tick, how many digests, what follows),
    the tick's rows of x, P and d, of d_valid, reported, fused and live
    (when ``rec`` holds it), its digests (``tick_digests``) and, when the
    run has any, the rejoins and starting states pickled."""
    t = k - 1
    live = getattr(rec, "live", None)
    rows, cols, values = rec.tick_digests(k)
    rejoins, starts = getattr(rec, "rejoins", None), list(getattr(rec, "starts", ()))
    extra = pickle.dumps((rejoins, starts)) if rejoins or starts else b""
    return b"".join((HEADER.pack(k, len(rows), (live is not None) | (bool(extra) << 1)), rec.x[t].tobytes(),
                     rec.P[t].tobytes(), rec.d[t].tobytes(), rec.d_valid[t].tobytes(), rec.reported[t].tobytes(),
                     rec.fused[t].tobytes(), b"" if live is None else live[t].tobytes(), rows.tobytes(),
                     cols.tobytes(), values.tobytes(), extra))


def read_tick(data: bytes, rec) -> tuple:
    """``tick_bytes`` written into ``rec`` (a record of the run's shape):
    (the tick, its digests as ``tick_digests`` gives them)."""
    k, J, has = HEADER.unpack_from(data)
    t, at = k - 1, HEADER.size
    for name in ("x", "P", "d", "d_valid", "reported", "fused") + (("live",) if has & 1 else ()):
        row = getattr(rec, name)[t]
        size = row.nbytes
        row[...] = np.frombuffer(data, dtype=row.dtype, count=row.size, offset=at).reshape(row.shape)
        at += size
    if not has & 1:
        rec.live = None
    said = []
    for dtype in (np.intp, np.intp, np.uint64):
        said.append(np.frombuffer(data, dtype=dtype, count=J, offset=at))
        at += J * said[-1].itemsize
    rec.rejoins, rec.starts = pickle.loads(data[at:]) if has & 2 else ({}, [])
    return k, tuple(said)
