"""Worker processes that Ctrl-C stops at once.

A terminal sends Ctrl-C's SIGINT to every process of the foreground group,
workers included: ``process_pool``'s workers ignore it (the command alone
decides, and prints one line), and a block left by an exception (the
``KeyboardInterrupt``, a failed job) terminates the workers instead of
waiting for the jobs they run (``ProcessPoolExecutor``'s own exit waits).
"""
from __future__ import annotations

import signal
import sys
from contextlib import contextmanager

# Workers terminated mid-job leave the queues' semaphores to multiprocessing's
# resource tracker, which frees them and says so on stderr after the command's
# own last line; the tracker takes its warning filters from sys.warnoptions.
TRACKER_QUIET = "ignore:resource_tracker:UserWarning"


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextmanager
def process_pool(jobs: int, context=None):
    """A ``ProcessPoolExecutor`` of ``jobs`` workers (``context``: a
    multiprocessing context, e.g. ``get_context("spawn")``)."""
    from concurrent.futures import ProcessPoolExecutor

    if TRACKER_QUIET not in sys.warnoptions:  # before the first pool starts the tracker
        sys.warnoptions.append(TRACKER_QUIET)
    pool = ProcessPoolExecutor(jobs, mp_context=context, initializer=_ignore_sigint)
    try:
        yield pool
    except BaseException:
        for worker in list((pool._processes or {}).values()):  # the executor has no public terminate
            worker.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
