"""Live runs in Foxglove or Lichtblick: ``diskf-mesh up --live [PORT]``.

The world starts a foxglove-sdk WebSocket server (``live.server``) on
127.0.0.1 and feeds it every closed tick, as it feeds the recorder; the
server publishes the channels of a recording (``recording.schemas``,
``/scene``), so a viewer opens a running mesh as it opens a recording.
Open ``ws://127.0.0.1:PORT`` in Foxglove or Lichtblick (Open connection,
Foxglove WebSocket); from another machine through ``ssh -L`` (docs/live.md).

``add_arguments`` is the flag of ``up`` and ``world``; ``check_port`` and
``feed`` are their hooks.

May import: every layer but cli.
"""
from __future__ import annotations

import argparse
import socket

from diskf_mesh.core.errors import InputError
from diskf_mesh.recording.writer import NoRecorder

DEFAULT_PORT = 8765  # Foxglove's default for a WebSocket connection


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--live", type=int, nargs="?", const=DEFAULT_PORT, default=None, metavar="PORT",
                        help="serve the run live to Foxglove or Lichtblick at ws://127.0.0.1:PORT "
                             f"(default port {DEFAULT_PORT}; docs/live.md)")


def check_port(port: int) -> None:
    """An ``InputError`` unless ``port`` is free on 127.0.0.1."""
    if not 1 <= port <= 65535:
        raise InputError("live", f"port must be 1 to 65535, got {port}")
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError as e:
            raise InputError("live", f"port {port} is not free on 127.0.0.1: {e.strerror or e}") from None


class Both(NoRecorder):
    """The world's hooks to the recorder and to the live server."""

    def __init__(self, recorder: NoRecorder, live: NoRecorder):
        self.recorder, self.live = recorder, live

    def on_open(self, k, live):
        self.recorder.on_open(k, live)
        self.live.on_open(k, live)

    def on_report(self, report):
        self.recorder.on_report(report)
        self.live.on_report(report)

    def on_close(self, k, missing):
        self.recorder.on_close(k, missing)
        self.live.on_close(k, missing)

    def finish(self, status, metrics=None, verification=None):
        """The recorder's failure, if any (the live server's is on its stderr)."""
        self.live.finish(status, metrics, verification)
        return self.recorder.finish(status, metrics, verification)


def feed(recorder: NoRecorder, port: int, trace, scn, **run) -> NoRecorder:
    """``recorder`` and the live server on ``port`` (``run``: ``Recorder``'s
    keywords), fed by the same hooks."""
    from diskf_mesh.live.server import LiveFeed

    return Both(recorder, LiveFeed(port, trace, scn, **run))
