"""cli: the ``diskf-mesh`` command line, one module per command.

``main`` builds the parser from every command module (``register``), and
turns an InputError into one ``error:`` line with exit status 2. The mesh's
commands (``up``, ``world``, ``agent``) live with their processes in
``sim/`` and ``agents/`` of the repository.

Installed, those two folders are inside the package, in ``diskf_mesh/_apps``
(the only top-level package ``pip install`` adds is ``diskf_mesh``); this
module puts that folder first on the command line's import path, and on its
children's (``PYTHONPATH``), so a process of a run imports ``sim`` and
``agents`` as in the repository, and no other package of those names.

Ctrl-C while the command line itself is still being imported (before
``main`` runs, which then says ``interrupted`` and exits 130) prints the
same one line instead of an import traceback: ``interrupted_quietly``,
installed here, the first module of the command line to load.

Every command and every process of a run uses one BLAS thread
(``BLAS_ENV``, set here before numpy loads, unless the environment says
otherwise; ``sim`` and ``agents`` import this module first, so a process
started as ``python -m sim.world`` or ``agents.agent`` does too): the
estimators' matrices are a few rows each and their sums over senders are
numpy's own loops (``core.linalg.nbr_sum``), so a second BLAS thread does
none of the work, while its start and its spinning cost CPU
(docs/performance.md, Table II as one command). The results are the same
bits either way.

May import: every layer of diskf_mesh.
"""
import os
import sys

# one BLAS thread: for the command line and the processes of a run (where the caller sets none), and for the
# zygote, which must fork as a single thread (``sim.zygote``)
BLAS_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
APPS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "_apps")


def interrupted_quietly(kind, value, tb) -> None:
    """``sys.excepthook``: an uncaught KeyboardInterrupt is one line."""
    if issubclass(kind, KeyboardInterrupt):
        print("interrupted", file=sys.stderr, flush=True)
        os._exit(130)  # as main's own Ctrl-C; nothing has started that needs cleaning up
    sys.__excepthook__(kind, value, tb)


def find_apps() -> None:
    """``diskf_mesh/_apps`` (the processes' ``sim`` and ``agents``) first on
    this process's import path and its children's."""
    if not os.path.isdir(os.path.join(APPS, "sim")):
        return
    if APPS not in sys.path:
        sys.path.insert(0, APPS)
    paths = os.environ.get("PYTHONPATH", "").split(os.pathsep) if os.environ.get("PYTHONPATH") else []
    if APPS not in paths:
        os.environ["PYTHONPATH"] = os.pathsep.join([APPS, *paths])


for _name, _value in BLAS_ENV.items():
    os.environ.setdefault(_name, _value)
if sys.excepthook is sys.__excepthook__:
    sys.excepthook = interrupted_quietly
find_apps()
