"""The fork server: a forked child is the process its command line stands
for, run as ``python -m`` runs it (the module's own ``__main__``), its exit
status the one that process gives, its command line the one it stands for."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from sim import zygote

pytestmark = pytest.mark.skipif(not zygote.enabled(), reason="the zygote forks on Linux only")


@pytest.fixture(scope="module")
def server():
    z = zygote.Zygote()
    yield z
    z.close()


def _fork(server, tmp_path: Path, *args):
    err = tmp_path / "err"
    with err.open("wb") as f:
        proc = server.spawn([sys.executable, "-m", "sim.host", *args], subprocess.PIPE, f)
    assert proc is not None, server.why
    out = proc.stdout.read().decode()
    proc.wait(60)
    return proc, out, err.read_text()


def test_a_forked_child_runs_its_modules_main(server, tmp_path):
    """``sim.host --help``: argparse of the host's ``__main__`` prints its
    usage on the child's stdout and exits 0."""
    proc, out, err = _fork(server, tmp_path, "--help")
    assert proc.returncode == 0, err
    assert out.startswith("usage: diskf-mesh host ")
    assert proc.args == [sys.executable, "-m", "sim.host", "--help"]


def test_a_forked_childs_exit_status_is_its_own(server, tmp_path):
    """An unknown option: the host's one-line error on the child's stderr
    and its exit status 2, as ``python -m sim.host --bogus`` gives."""
    proc, out, err = _fork(server, tmp_path, "--bogus")
    direct = subprocess.run([sys.executable, "-m", "sim.host", "--bogus"], capture_output=True, text=True)
    assert direct.returncode == 2
    assert (proc.returncode, out, err) == (direct.returncode, direct.stdout, direct.stderr)
