"""The live view of a mesh run in a browser: ``diskf-mesh up --live [PORT]``.

The view is Rerun's web viewer (the ``rerun-sdk`` wheel ships it, HTML, JS
and Wasm, and its server: nothing comes from the internet), fed by a viewer
process (``diskf_mesh.live.viewer``) that listens to the run on zenoh and
recomputes the truth from the scenario and the seed. The world and the agents
do not change, and while no browser is connected the viewer has no zenoh
session at all. What it shows: ``diskf_mesh.live.view``.

``add_arguments`` and ``attach`` are the launcher's hook: ``up --live``
starts the viewer as one more child of the run (stopped with the others).
"""
from __future__ import annotations

import argparse
import importlib.util
import socket
import subprocess
import sys

from ..errors import InputError

DEFAULT_PORT = 9090
MODULE = "diskf_mesh.live.viewer"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--live", type=int, nargs="?", const=DEFAULT_PORT, default=None, metavar="PORT",
                        help="serve a live view of the run at http://127.0.0.1:PORT/ (default port "
                             f"{DEFAULT_PORT}; needs the rerun-sdk package: pip install 'diskf-mesh[live]')")


def _check_port(port: int) -> None:
    if not 1 <= port <= 65535:
        raise InputError("live", f"port must be 1 to 65535, got {port}")
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError as e:
            raise InputError("live", f"port {port} is not free on 127.0.0.1: {e.strerror or e}") from None


def viewer_command(spec, ticks: int, seed: int, port: int, grpc_port: int, zenoh, status=None) -> list:
    """argv of the viewer process (``zenoh``: its ``ZenohOptions``)."""
    return [sys.executable, "-m", MODULE, *spec.to_argv(), "--ticks", str(ticks), "--seed", str(seed),
            "--port", str(port), "--grpc-port", str(grpc_port), *zenoh.to_argv(),
            *(["--status", str(status)] if status else [])]


def attach(args, launcher, spec, ticks: int, zenoh, logs):
    """With ``--live``: start the viewer as a child of ``launcher`` (it is
    stopped with the others) and print the address to open; ``zenoh`` are the
    viewer's session options. Returns the child, or None without ``--live``."""
    if args.live is None:
        return None
    from sim.launcher import Child, free_port  # the launcher calls this hook: no import cycle at load time

    _check_port(args.live)
    if importlib.util.find_spec("rerun") is None:
        raise InputError("live", "the live view needs the rerun-sdk package: pip install 'diskf-mesh[live]'")
    from .viewer import page_url

    grpc_port = free_port()
    child = Child("live view", viewer_command(spec, ticks, args.seed, args.live, grpc_port, zenoh,
                                              logs / "live-status.json"), logs / "live.log")
    launcher._spawn(child, subprocess.DEVNULL)
    launcher.children.append(child)
    print(f"live view: {page_url(args.live, grpc_port)}", file=sys.stderr, flush=True)
    return child
