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
from diskf_mesh.cli import main as cli
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
    ["experiment", "--seeds", "1", "--ticks", "5", "--algorithms", "diskf"],
    ["simulate", "--ticks", "5", "--out", "trace.json"],
], ids=lambda a: " ".join(a))
def test_commands_that_draw_nothing_load_no_plotting_library(argv, tmp_path):
    done, loaded = run(argv, tmp_path)
    assert done.returncode == 0, done.stderr
    assert loaded == ""


def test_replay_loads_no_plotting_library(tmp_path):
    assert run(["simulate", "--ticks", "5", "--out", "trace.json"], tmp_path)[0].returncode == 0
    done, loaded = run(["replay", "trace.json", "--out", "est.json"], tmp_path)
    assert done.returncode == 0 and loaded == ""


def test_version(tmp_path):
    done, _ = run(["--version"], tmp_path)
    assert done.returncode == 0 and done.stdout == f"diskf-mesh {__version__}\n"


def test_figures_without_the_figures_extra_is_one_error_line(tmp_path):
    """matplotlib is the optional 'figures' extra: without it, figures ends
    in one line saying how to install it, exit 2, nothing written."""
    probe = "import sys; sys.modules['matplotlib'] = None\n" + PROBE
    out = tmp_path / "figs"
    done = subprocess.run([sys.executable, "-c", probe, "figures", "--out", str(out), "--seeds", "1", "--ticks", "5"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == ""
    errors = [line for line in done.stderr.splitlines() if not line.startswith("LOADED")]
    assert len(errors) == 1 and errors[0].startswith("error: figures: ")
    assert errors[0].endswith("pip install '.[figures]' in the diskf-mesh folder")  # the README's install
    assert not out.exists()


def test_a_command_loads_its_own_module_alone(tmp_path):
    """A command loads no other command's module (it starts faster);
    without a command, --help lists every one."""
    probe = ("import sys\nfrom diskf_mesh.cli import main as cli\ntry:\n    cli.main(sys.argv[1:])\n"
             "except SystemExit:\n    pass\n"
             "print('LOADED', ','.join(sorted(set(cli.COMMAND_MODULES) & set(sys.modules))), file=sys.stderr)\n")
    loaded = {}
    for argv in (["experiment", "--help"], ["replay", "--help"], ["--help"]):
        done = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True, text=True, cwd=tmp_path,
                              timeout=120)
        loaded[argv[0]] = done.stderr.rsplit("LOADED", 1)[1].strip().split(",")
    assert loaded["experiment"] == ["diskf_mesh.cli.experiment"]
    assert loaded["replay"] == ["diskf_mesh.cli.replay"]
    assert sorted(loaded["--help"]) == sorted(__import__("diskf_mesh.cli.main").cli.main.COMMAND_MODULES)


THREADS = """
import os, sys
import %s
print(len(os.listdir('/proc/self/task')), os.environ['OPENBLAS_NUM_THREADS'])
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/task")
@pytest.mark.parametrize("module", ["diskf_mesh.cli.main", "sim.world", "agents.agent"])
def test_the_command_line_runs_on_one_blas_thread_unless_told_otherwise(tmp_path, module):
    """numpy loaded by the command line, or by a process of a run started
    as ``python -m`` (a container's), starts no BLAS thread beside the main
    one (its matrices are small: a second thread costs CPU and does no
    work); a caller's own setting is kept."""
    import os

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                            "MKL_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    probe = THREADS % module
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path, env=env,
                          timeout=120)
    assert done.stdout.split() == ["1", "1"], done.stderr
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path,
                          env={**env, "OPENBLAS_NUM_THREADS": "2"}, timeout=120)
    assert done.stdout.split()[1] == "2", done.stderr
