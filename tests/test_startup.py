"""Start-up: --help, --version and the commands that draw nothing load no
plotting library (matplotlib, PIL) and no scipy; each runs in a fresh
interpreter, as a user's shell would start it."""
from __future__ import annotations

import subprocess
import sys

import pytest

from diskf_mesh import __version__

HEAVY = ("matplotlib", "PIL", "scipy")
PROBE = """
import sys
from diskf_mesh import cli
try:
    code = cli.main(sys.argv[1:])
except SystemExit as e:
    code = e.code
loaded = sorted({m.split('.')[0] for m in sys.modules} & set(%r))
print('LOADED', ','.join(loaded), file=sys.stderr)
sys.exit(code)
""" % (HEAVY,)


def run(argv, cwd):
    done = subprocess.run([sys.executable, "-c", PROBE, *map(str, argv)], capture_output=True, text=True,
                          cwd=cwd, timeout=120)
    loaded = done.stderr.rsplit("LOADED", 1)[1].strip()
    return done, loaded


@pytest.mark.parametrize("argv", [
    ["--help"], ["experiment", "--help"], ["up", "--help"],
    ["experiment", "--seeds", "1", "--steps", "5", "--algorithms", "diskf"],
    ["simulate", "--steps", "5", "--out", "trace.json"],
], ids=lambda a: " ".join(a))
def test_commands_that_draw_nothing_load_no_plotting_library(argv, tmp_path):
    done, loaded = run(argv, tmp_path)
    assert done.returncode == 0, done.stderr
    assert loaded == ""


def test_replay_loads_no_plotting_library(tmp_path):
    assert run(["simulate", "--steps", "5", "--out", "trace.json"], tmp_path)[0].returncode == 0
    done, loaded = run(["replay", "trace.json", "--out", "est.json"], tmp_path)
    assert done.returncode == 0 and loaded == ""


def test_version(tmp_path):
    done, _ = run(["--version"], tmp_path)
    assert done.returncode == 0 and done.stdout == f"diskf-mesh {__version__}\n"
