"""How a mesh process stops on a signal, at any moment of its life.

A process of a run installs its handlers first thing in its ``run(args)``:

    world    SIGTERM/SIGINT end the run at the next look (at most ``POLL_S``
             later); its results are written, marked interrupted, and it
             exits 3 (incomplete)
    agent    SIGTERM raises ``SystemExit(143)`` (``terminated``): the
             process leaves through its ``finally`` blocks (its zenoh
             session closed) and exits 143, the status a shell shows for a
             process SIGTERM ended; Ctrl-C (SIGINT) likewise exits 130. A
             Python handler runs only between two bytecodes of the main
             thread, not while it waits inside zenoh (a session that cannot
             reach its router, a close): ``exit_on_sigterm``'s watchdog
             thread, woken by the signal itself (``signal.set_wakeup_fd``),
             ends the process with 143 if it is still there ``GRACE_S``
             later
    host, up SIGTERM raises ``SystemExit(143)``: their children are
             stopped (SIGTERM) on the way out
    router   SIGTERM/SIGINT: exits 0 (serving until stopped is its job)

Every command of the command line (``cli.main``) raises SIGTERM as
``SystemExit(143)`` and SIGINT as ``Interrupted`` (a ``KeyboardInterrupt``),
each at the first bytecode outside the import machinery
(``later_if_importing``): raised inside an import, the exception may be
dropped, turned into another, or make CPython end the process by SIGINT.

Before its handler is installed (while the interpreter imports), a process
keeps the default action, which ends it at once; except as PID 1 of a
container, where the kernel ignores a signal that has no handler: run the
image with an init (``init: true`` in the compose files, ``docker run
--init``), which forwards the signal to the process.
"""
from __future__ import annotations

import os
import signal
import threading

GRACE_S = 1.5  # SIGTERM -> exit at the latest this much later (a container's stop waits 10 s, up's 3 s)
RECHECK_S = 0.02  # a signal that came during an import is delivered again this much later


def terminated(signum, frame):
    """A signal handler: the signal as ``SystemExit(128 + signum)``, raised
    where no import is under way (``later_if_importing``)."""
    if not later_if_importing(signum, frame):
        raise SystemExit(128 + signum)


class Interrupted(KeyboardInterrupt):
    """SIGINT as ``interrupted`` raises it: a ``KeyboardInterrupt`` to every
    ``except`` clause, but not of the exact type, which CPython takes for an
    unhandled Ctrl-C when it leaves code run by ``exec`` of a string (the
    methods a dataclass generates) and then ends the process by SIGINT at
    exit (status -2) even though the command caught it and returned 130."""


def interrupted(signum, frame):
    """A SIGINT handler: ``Interrupted``, raised where no import is under way."""
    if not later_if_importing(signum, frame):
        raise Interrupted


def later_if_importing(signum: int, frame) -> bool:
    """Whether ``frame`` (where the main thread was when the signal came) is
    inside the import machinery; if so, the signal is delivered again
    ``RECHECK_S`` later, and the handler should return without raising. An
    exception raised inside an import is not always the one that leaves it:
    a module lock's weakref callback prints and drops it (the command then
    runs on as if no signal had come), and a class's ``__set_name__`` turns
    it into a RuntimeError (exit 1, with a traceback)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            threading.Timer(RECHECK_S, signal.pthread_kill, args=(threading.main_thread().ident, signum)).start()
            return True
        frame = frame.f_back
    return False


def exit_on_sigterm(grace_s: float = GRACE_S) -> None:
    """From here on SIGTERM raises ``SystemExit(143)`` in the main thread,
    and the process ends with 143 ``grace_s`` later if it has not by then.
    Main thread only; the watchdog is left out if something else already
    owns the signal wake-up fd."""
    signal.signal(signal.SIGTERM, terminated)
    read, write = os.pipe()
    os.set_blocking(write, False)
    if (other := signal.set_wakeup_fd(write, warn_on_full_buffer=False)) != -1:  # someone else's: give it back
        signal.set_wakeup_fd(other)
        os.close(read)
        os.close(write)
        return
    threading.Thread(target=_watchdog, args=(read, grace_s), name="sigterm-watchdog", daemon=True).start()


def _watchdog(read: int, grace_s: float) -> None:
    while signal.SIGTERM not in os.read(read, 64):
        pass
    threading.Event().wait(grace_s)
    os._exit(128 + signal.SIGTERM)
