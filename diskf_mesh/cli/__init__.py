"""cli: the ``diskf-mesh`` command line, one module per command.

``main`` builds the parser from every command module (``register``), and
turns an InputError into one ``error:`` line with exit status 2. The mesh's
commands (``up``, ``world``, ``agent``) live with their processes in
``sim/`` and ``agents/``.

Ctrl-C while the command line itself is still being imported (before
``main`` runs, which then says ``interrupted`` and exits 130) prints the
same one line instead of an import traceback: ``interrupted_quietly``,
installed here, the first module of the command line to load.

May import: every layer of diskf_mesh.
"""
import os
import sys


def interrupted_quietly(kind, value, tb) -> None:
    """``sys.excepthook``: an uncaught KeyboardInterrupt is one line."""
    if issubclass(kind, KeyboardInterrupt):
        print("interrupted", file=sys.stderr, flush=True)
        os._exit(130)  # as main's own Ctrl-C; nothing has started that needs cleaning up
    sys.__excepthook__(kind, value, tb)


if sys.excepthook is sys.__excepthook__:
    sys.excepthook = interrupted_quietly
