"""The world's check as the run goes, in a process of its own beside the world.

``CheckProcess`` has the interface of ``mesh.protocol.run_status.OnlineCheck``
that ``WorldMachine`` calls (``submit``, ``result``): ``submit(rec, k)``
sends tick k's reports (its rows of the record, the digests, rejoins and
starting states) down a pipe to a child process, forked before the world's
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
import signal
import time
import traceback

import numpy as np

from diskf_mesh.mesh.protocol.world_machine import WorldRecord
from diskf_mesh.mesh.protocol.reports import RunReports

NICE = 5       # steps of niceness below the world (os.nice)
JOIN_S = 2.0   # at the end, for the child to leave before it is terminated


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
        t, N = k - 1, rec.reported.shape[1]
        digests = {(k, i): rec.digests[(k, i)] for i in range(N) if (k, i) in rec.digests}
        live = getattr(rec, "live", None)
        # the tick's rows as raw bytes (its floats, then its flags), the rest as it is (mostly empty)
        floats = b"".join((rec.x[t].tobytes(), rec.P[t].tobytes(), rec.d[t].tobytes()))
        flags = b"".join((rec.d_valid[t].tobytes(), rec.reported[t].tobytes(), rec.fused[t].tobytes(),
                          b"" if live is None else live[t].tobytes()))
        try:
            self._conn.send((k, floats, flags, digests, getattr(rec, "rejoins", None) or None,
                             list(getattr(rec, "starts", ())) or None))
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
                kind, tick, value, self.cpu_s = self._conn.recv()
            except (EOFError, OSError):  # the child is gone
                raise self._ended(k) from None
            if kind == "error":
                raise CheckFailed(f"the online check failed at tick {tick}:\n{value}")
            if kind == "ready":
                self._ready_cpu_s = self.cpu_s
                continue
            self._found[tick] = value
        return self._found.pop(k)

    def _ended(self, k: int) -> CheckFailed:
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


def _check_each(make, conn) -> None:
    """Make the check, then check each tick as it comes; the pipe's end
    raises (``EOFError``, ``ConnectionError``)."""
    try:
        check = make()
    except Exception:  # noqa: BLE001 - the world raises it when it asks (its own setup fails the same way first)
        conn.send(("error", 0, traceback.format_exc(), time.process_time()))
        return
    conn.send(("ready", 0, None, time.process_time()))
    B, K, N = check.trace.has.shape
    n, m = check.trace.model.n, check.trace.model.m
    rec = WorldRecord(**RunReports.empty(K, N, n, m), live=np.zeros((K, N), dtype=bool))
    at = np.cumsum([0, N * n, N * n * n, N * m])  # where x, P, d lie in a tick's floats
    while True:
        k, floats, flags, digests, rejoins, starts = conn.recv()
        t, a, b = k - 1, np.frombuffer(floats, dtype=float), np.frombuffer(flags, dtype=bool)
        rec.x[t], rec.P[t], rec.d[t] = (a[at[0]:at[1]].reshape(N, n), a[at[1]:at[2]].reshape(N, n, n),
                                        a[at[2]:at[3]].reshape(N, m))
        rec.d_valid[t], rec.reported[t], rec.fused[t] = b[:N], b[N:2 * N], b[2 * N:2 * N + N * N].reshape(N, N)
        if b.size > 2 * N + N * N:
            rec.live[t] = b[2 * N + N * N:]
        else:
            rec.live = None
        rec.digests, rec.rejoins, rec.starts = digests, rejoins or {}, starts or []
        try:
            found = check.tick(rec, k)
        except Exception:  # noqa: BLE001 - the world raises it
            conn.send(("error", k, traceback.format_exc(), time.process_time()))
            return
        conn.send(("found", k, found, time.process_time()))
