"""How a mesh process stops on a signal, at any moment of its life.

A process of a run installs its handlers first thing in its ``run(args)``:

    world    SIGTERM/SIGINT end the run at the next look (at most ``POLL_S``
             later); its results are written, marked interrupted, and it
             exits 3 (incomplete)
    agent, host, up
             SIGTERM raises ``SystemExit(143)`` (``terminated``): the
             process leaves through its ``finally`` blocks (its zenoh
             session closed, a host's or up's children stopped) and exits
             143, the status a shell shows for a process SIGTERM ended;
             Ctrl-C (SIGINT) likewise exits 130
    router   SIGTERM/SIGINT: exits 0 (serving until stopped is its job)

Before its handler is installed (while the interpreter imports), a process
keeps the default action, which ends it at once; except as PID 1 of a
container, where the kernel ignores a signal that has no handler: run the
image with an init (``init: true`` in the compose files, ``docker run
--init``), which forwards the signal to the process.
"""
from __future__ import annotations

import signal


def terminated(signum, frame):
    """A signal handler: the signal as ``SystemExit(128 + signum)``."""
    raise SystemExit(128 + signum)


def exit_on_sigterm():
    """SIGTERM raises ``SystemExit(143)`` from here on; returns the handler
    it replaces."""
    return signal.signal(signal.SIGTERM, terminated)
