"""The live view of one mesh run, in its own process (``up --live`` starts it).

    python -m diskf_mesh.live.viewer --scenario dynamic --ticks 200 --seed 0 --run-id ID \\
        --port 9090 [zenoh flags] [--status FILE]

It serves, on 127.0.0.1 only, one page (``page.html``: plain JS drawing SVG,
nothing loaded from elsewhere) at ``/``, the run's fixed scene at
``/scene`` and the frames as Server-Sent Events at ``/events``.

Nothing happens on the mesh while nobody watches: the viewer holds a zenoh
session, subscribed to the run's ticks, reports and stop, only while at
least one page is connected to ``/events``. With no page open there is no
extra subscriber on the mesh at all, and the world and the agents never
change either way: they publish what they always publish. A page opened at
tick k shows the run from tick k on (and the target's true path); it
keeps what it got after the run ended.

The mesh ticks faster than a screen needs: the newest tick goes to the pages
at most ``1 / FRAME_S`` times a second and the ticks between are skipped (the
running error still counts them).

``--status FILE`` writes ``{"viewers", "watching", "frames", "shown", "tick",
"late"}`` after every poll (for tests and scripts: pages connected, ticks
heard, frames sent, the tick of the last one, reports that came too late).
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources

from diskf_mesh.mesh import wire
from diskf_mesh.data.argtypes import positive_int, seed_value
from diskf_mesh.data.outputs import atomic_open
from diskf_mesh.mesh import credentials
from diskf_mesh.mesh import runspec
from diskf_mesh.mesh import zenoh_config
from diskf_mesh.mesh.keys import Keys
from diskf_mesh.mesh.log import Log
from diskf_mesh.mesh.transport import MeshError, ZenohTransport
from diskf_mesh.mesh.zenoh_config import ZenohOptions
from diskf_mesh.data.scenario import simulate
from diskf_mesh.live import DEFAULT_PORT
from diskf_mesh.live.view import LiveView, frame_doc, scene_doc

HOST = "127.0.0.1"
POLL_S = 0.2        # how often it looks whether anybody watches, and writes --status
FRAME_S = 0.1       # at most one frame this often to the pages (10 per second)
KEEPALIVE_S = 10.0  # an SSE comment this often when no frame comes (a page that left is noticed)


def page_url(port: int) -> str:
    """The address a browser on this machine opens."""
    return f"http://{HOST}:{port}/"


class Broadcast:
    """The newest frame (as SSE bytes) and the number of pages listening."""

    def __init__(self):
        self._cv = threading.Condition()
        self.seq = 0
        self.data = b""
        self.listeners = 0
        self.closed = False

    def publish(self, doc: dict) -> None:
        data = b"data: " + json.dumps(doc, separators=(",", ":")).encode() + b"\n\n"
        with self._cv:
            self.seq, self.data = self.seq + 1, data
            self._cv.notify_all()

    def next(self, seen: int, timeout: float) -> tuple:
        """(seq, data) newer than ``seen``, or (seen, b"") after ``timeout``."""
        with self._cv:
            self._cv.wait_for(lambda: self.seq != seen or self.closed, timeout)
            return (self.seq, self.data) if self.seq != seen else (seen, b"")

    def join(self, delta: int) -> None:
        with self._cv:
            self.listeners += delta

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()


def make_server(port: int, page: bytes, scene: bytes, frames: Broadcast) -> ThreadingHTTPServer:
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, *args):  # no line per request
            pass

        def _send(self, body: bytes, ctype: str) -> None:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self):
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                self._send(page, "text/html; charset=utf-8")
            elif path == "/scene":
                self._send(scene, "application/json")
            elif path == "/events":
                self._events()
            else:
                self.send_error(HTTPStatus.NOT_FOUND)

        def _events(self) -> None:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            frames.join(+1)
            seen = 0
            try:
                while not frames.closed:
                    seen, data = frames.next(seen, KEEPALIVE_S)
                    self.wfile.write(data or b": keep-alive\n\n")
                    self.wfile.flush()
            except (BrokenPipeError, ConnectionResetError):
                pass
            finally:
                frames.join(-1)
                self.close_connection = True

    server = ThreadingHTTPServer((HOST, port), Handler)
    server.daemon_threads = True
    return server


# --------------------------------------------------------------------------
# the mesh side
# --------------------------------------------------------------------------
def open_transport(options: ZenohOptions) -> ZenohTransport:
    """The one place the view opens its zenoh session: ``options`` come from
    the caller (``up --live`` passes an agent's options; with access control,
    an identity allowed to subscribe only)."""
    return ZenohTransport(options)


class Watch:
    """A zenoh session subscribed to the run's ticks, reports and stop, feeding
    ``view``; open only while somebody watches."""

    def __init__(self, options: ZenohOptions, keys: Keys, view: LiveView, log: Log):
        self.keys, self.view, self.log = keys, view, log
        self.transport = open_transport(options)
        self.transport.subscribe(keys.tick, self._on_sample)
        self.transport.subscribe(f"{keys.root}/agent/*/report", self._on_sample)
        self.transport.subscribe(keys.stop, self._on_sample)

    def _on_sample(self, key: str, payload: bytes) -> None:
        kind, who = self.keys.parse(key)
        run, v = self.keys.run_id, self.view
        try:
            if kind == "tick":
                v.on_tick(wire.decode_tick(payload, run_id=run, agents=len(v.ids)))
            elif kind == "report" and who in v.index:
                v.on_report(wire.decode_report(payload, run_id=run, sender=who, n=v.n, m=v.m))
            elif kind == "stop":
                wire.decode_stop(payload, run_id=run)
                v.on_stop()
        except wire.Rejected as e:
            self.log.once(("rejected", key, e.reason), f"ignored {key}: {e}")

    def close(self) -> None:
        self.transport.close()


def write_status(path: str | None, **status) -> None:
    if not path:
        return
    with atomic_open(path, "w", "status") as f:  # a viewer killed while writing leaves no temporary file
        json.dump(status, f)


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def register(subparsers) -> None:
    p = subparsers.add_parser("live", help="the live view of a mesh run, in a browser",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    runspec.add_arguments(p)
    p.add_argument("--ticks", type=positive_int, metavar="K", help="ticks of the run (default: the scenario's steps)")
    p.add_argument("--seed", type=seed_value, default=0, metavar="S", help="the run's seed (default 0)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="HTTP port on 127.0.0.1 (default %(default)s)")
    p.add_argument("--status", metavar="FILE", help="write what went to the view after every poll")
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    spec = runspec.from_args(args)
    scn = spec.load(args.ticks)
    trace = simulate(scn, [args.seed])
    log = Log("live")
    options = zenoh_config.from_args(args, credentials.OBSERVER, spec.run_id)  # listens only (docs/security.md)
    keys = Keys(spec.run_id)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # the launcher's stop: clean up below
    page = resources.files(__package__).joinpath("page.html").read_bytes()
    scene = json.dumps(scene_doc(scn, trace, spec.run_id, spec.algorithm)).encode()
    frames = Broadcast()
    try:
        server = make_server(args.port, page, scene, frames)
    except OSError as e:
        log.error(f"cannot serve on {HOST}:{args.port}: {e.strerror or e}")
        return 1
    threading.Thread(target=server.serve_forever, name="http", daemon=True).start()
    view = LiveView(scn, trace)
    watch = None
    shown, tick, next_poll = 0, 0, 0.0
    try:
        while True:
            frame = view.take()
            if frame is not None:
                frames.publish(frame_doc(frame, view.ids))
                shown, tick = shown + 1, frame.tick
            if time.monotonic() >= next_poll:
                next_poll = time.monotonic() + POLL_S
                if frames.listeners and watch is None:
                    watch = Watch(options, keys, view, log)
                elif not frames.listeners and watch is not None:
                    watch.close()
                    watch = None
                write_status(args.status, viewers=frames.listeners, watching=watch is not None,
                             frames=view.frames, shown=shown, tick=tick, late=view.late)
            time.sleep(FRAME_S if watch is not None else POLL_S)
    except MeshError as e:
        log.error(str(e))
        return 1
    finally:
        if watch is not None:
            watch.close()
        frames.close()
        server.shutdown()
        server.server_close()


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("live", __spec__.name))
