"""SIGTERM ends a mesh process at any moment (diskf_mesh.mesh.process.stopping):
through its finally blocks when the main thread runs Python, and within
GRACE_S when it waits inside zenoh, where no Python handler can run."""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from diskf_mesh.mesh.process.stopping import GRACE_S

PRELUDE = "import sys\nfrom diskf_mesh.mesh.process.stopping import exit_on_sigterm\nexit_on_sigterm()\n"


def _sigterm_when_ready(code: str) -> tuple:
    """Run ``code`` after the prelude, SIGTERM it once it prints 'ready';
    (exit status, seconds from SIGTERM to exit, its stdout)."""
    proc = subprocess.Popen([sys.executable, "-c", PRELUDE + code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.2)
        began = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        status = proc.wait(GRACE_S + 10)
        return status, time.monotonic() - began, proc.stdout.read()
    finally:
        proc.kill()
        proc.wait()


def test_sigterm_in_python_code_leaves_through_the_finally_blocks():
    status, took, out = _sigterm_when_ready(
        "import time\ntry:\n    print('ready', flush=True)\n    time.sleep(30)\n"
        "finally:\n    print('closed', flush=True)\n")
    assert status == 128 + signal.SIGTERM and out.strip() == "closed"
    assert took < GRACE_S


@pytest.mark.mesh
def test_sigterm_while_zenoh_waits_for_an_unreachable_router_ends_the_process_in_grace():
    """A client session opening towards a router that is not there blocks
    inside zenoh without a timeout; the handler cannot run, the watchdog
    ends the process."""
    status, took, _ = _sigterm_when_ready(
        "import zenoh\nc = zenoh.Config()\nc.insert_json5('mode', '\"client\"')\n"
        "c.insert_json5('connect/endpoints', '[\"tcp/127.0.0.1:9\"]')\nc.insert_json5('connect/timeout_ms', '-1')\n"
        "print('ready', flush=True)\nzenoh.open(c)\nprint('opened', flush=True)\n")
    assert status == 128 + signal.SIGTERM
    assert GRACE_S - 0.1 < took < GRACE_S + 1.0


IMPORTED_UNDER_A_SIGNAL = '''
import os, signal, sys, time
from dataclasses import dataclass
os.kill(os.getpid(), signal.SIG)
@dataclass(frozen=True)
class Made:
    a: int = 1
    b: float = 2.0
DONE = True
'''


@pytest.mark.parametrize("name, handler, caught", [
    ("SIGINT", "interrupted", "KeyboardInterrupt"), ("SIGTERM", "terminated", "SystemExit")])
def test_a_signal_during_an_import_is_raised_after_it(tmp_path, name, handler, caught):
    """The signal comes while a module is being imported (its dataclass's
    methods are made by exec); the import completes and the signal is
    raised just after it, where the command's own except clause catches it:
    raised inside, it can be dropped by a module lock's callback, become a
    RuntimeError, or make CPython end the process by SIGINT (status -2)."""
    (tmp_path / "under_signal.py").write_text(IMPORTED_UNDER_A_SIGNAL.replace("signal.SIG", f"signal.{name}"))
    code = (f"import signal, sys, time\nfrom diskf_mesh.mesh.process import stopping\n"
            f"signal.signal(signal.{name}, stopping.{handler})\nsys.path.insert(0, {str(tmp_path)!r})\n"
            "try:\n    import under_signal\n    time.sleep(5)\n    sys.exit(1)\n"
            f"except {caught}:\n    print(sys.modules['under_signal'].DONE, flush=True)\n    sys.exit(130)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert (done.returncode, done.stdout.strip(), done.stderr) == (130, "True", "")
