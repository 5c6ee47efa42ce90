"""The live view of a mesh run in a browser: ``diskf-mesh up --live [PORT]``.

A viewer process (``diskf_mesh.live.viewer``) serves one page on 127.0.0.1
(plain JS drawing SVG, fed by Server-Sent Events; nothing comes from the
internet). It listens to the run on zenoh and recomputes the truth from the
scenario and the seed. The world and the agents do not change, and while no
page is open the viewer has no zenoh session at all. What it shows:
``diskf_mesh.live.view``.

``add_arguments`` and ``attach`` are the launcher's hook: ``up --live``
starts the viewer as one more child of the run (stopped with the others).

May import: every layer but cli.
"""
from __future__ import annotations

import argparse
import socket
import sys

from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh import credentials

DEFAULT_PORT = 9090
MODULE = "diskf_mesh.live.viewer"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--live", type=int, nargs="?", const=DEFAULT_PORT, default=None, metavar="PORT",
                        help="serve a live view of the run at http://127.0.0.1:PORT/ for a browser on this "
                             f"machine (default port {DEFAULT_PORT})")


def _check_port(port: int) -> None:
    if not 1 <= port <= 65535:
        raise InputError("live", f"port must be 1 to 65535, got {port}")
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError as e:
            raise InputError("live", f"port {port} is not free on 127.0.0.1: {e.strerror or e}") from None


def viewer_command(spec, ticks: int, seed: int, port: int, zenoh, status=None) -> list:
    """argv of the viewer process (``zenoh``: its ``ZenohOptions``)."""
    return [sys.executable, "-m", MODULE, *spec.to_argv(), "--ticks", str(ticks), "--seed", str(seed),
            "--port", str(port), *zenoh.to_argv(), *(["--status", str(status)] if status else [])]


def attach(args, launcher, spec, ticks: int, zenoh, logs):
    """With ``--live``: start the viewer as a child of ``launcher`` (it is
    stopped with the others) and print the address to open; ``zenoh`` are the
    viewer's session options. Returns the child, or None without ``--live``."""
    if args.live is None:
        return None
    from diskf_mesh.live.viewer import page_url

    _check_port(args.live)
    child = launcher.add_child("live view", viewer_command(spec, ticks, args.seed, args.live, zenoh,
                                                            logs / "live-status.json"), logs / "live.log",
                               identities=(credentials.OBSERVER,))
    print(f"live view: {page_url(args.live)}", file=sys.stderr, flush=True)
    return child
