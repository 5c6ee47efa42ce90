"""The live view of one mesh run, in its own process (``up --live`` starts it).

    python -m diskf_mesh.live.viewer --scenario dynamic --ticks 200 --seed 0 --run-id ID \\
        --port 9090 --grpc-port G [zenoh flags] [--status FILE]

It starts Rerun's own server (the ``rerun`` binary of the ``rerun-sdk``
wheel: the web viewer's HTML, JS and Wasm on ``--port``, and the gRPC
stream the page reads on ``--grpc-port``, both bound to 127.0.0.1 and
served from the wheel: no internet needed) and logs ``LiveView`` frames to it.

Nothing happens on the mesh while nobody watches: every ``POLL_S`` it looks
at the TCP connections to the gRPC port (``/proc/net/tcp``); only while a
viewer other than its own logging connection is connected does it hold a
zenoh session, subscribed to the run's ticks, reports and stop. The world
and the agents never change: they publish what they always publish, and
with no watcher there is no extra subscriber on the mesh at all. A browser
that opens the page at tick k sees the run from tick k on (and the
target's whole true path); one that keeps it open keeps every tick, also
after the run ended.

The mesh ticks faster than a screen needs: the newest tick goes to the view
at most ``1 / FRAME_S`` times a second, and the ticks between are skipped
(the running error still counts them).

``--status FILE`` writes ``{"viewers", "watching", "frames", "shown", "tick",
"late"}`` after every poll (for tests and scripts: ticks heard, ticks sent to
the view, the last of them).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .. import wire
from ..commands.options import positive_int, seed_value
from ..mesh import runspec, zenoh_config
from ..mesh.keys import Keys
from ..mesh.log import Log
from ..mesh.transport import MeshError, ZenohTransport
from ..mesh.zenoh_config import ZenohOptions
from ..scenario import simulate
from .view import LiveView, RerunSink, blueprint

POLL_S = 0.2            # how often it looks for viewers
FRAME_S = 0.05          # at most one frame this often to the view (20 per second); ticks between are skipped
SERVER_START_S = 30.0   # for Rerun's server to listen
SERVER_MEMORY = "512MiB"  # Rerun's server keeps this much of the run for viewers that connect later
HOST = "127.0.0.1"


def page_url(port: int, grpc_port: int) -> str:
    """The address a browser on this machine opens."""
    return f"http://{HOST}:{port}/?url=rerun%2Bhttp%3A%2F%2F{HOST}%3A{grpc_port}%2Fproxy"


def rerun_binary() -> Path:
    """The ``rerun`` executable shipped in the rerun-sdk wheel."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is None or spec.origin is None:
        raise MeshError("the live view needs the rerun-sdk package (pip install 'diskf-mesh[live]')")
    return Path(spec.origin).parent / "rerun"


def quiet_rerun_env(home: Path) -> dict:
    """An environment in which Rerun's analytics are off (its config file in a
    private directory) for the server and this process's SDK alike."""
    (home / "rerun").mkdir(parents=True, exist_ok=True)
    (home / "rerun" / "analytics.json").write_text(json.dumps({"analytics_enabled": False}))
    return {"XDG_CONFIG_HOME": str(home), "XDG_DATA_HOME": str(home)}


def _die_with_parent() -> None:
    import ctypes

    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


class RerunServer:
    """Rerun's web viewer and gRPC server, a child process bound to 127.0.0.1."""

    def __init__(self, port: int, grpc_port: int, log: Path):
        self.port, self.grpc_port = port, grpc_port
        argv = [str(rerun_binary()), "--serve-web", "--bind", HOST, "--web-viewer-port", str(port),
                "--port", str(grpc_port), "--server-memory-limit", SERVER_MEMORY]
        with open(log, "wb") as out:
            self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                         preexec_fn=_die_with_parent)
        deadline = time.monotonic() + SERVER_START_S
        while not (listening(port) and listening(grpc_port)):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise MeshError(f"Rerun's server did not start on ports {port}, {grpc_port} (log: {log})")
            time.sleep(0.05)

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://{HOST}:{self.grpc_port}/proxy"

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(3.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(3.0)


# --------------------------------------------------------------------------
# who is connected (Linux: /proc/net/tcp)
# --------------------------------------------------------------------------
ESTABLISHED = "01"
LISTEN = "0A"


def _tcp_table() -> list:
    """(local port, remote port, state, inode) of every TCP socket of this host."""
    rows = []
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(name).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            rows.append((int(f[1].rsplit(":", 1)[1], 16), int(f[2].rsplit(":", 1)[1], 16), f[3], f[9]))
    return rows


def listening(port: int) -> bool:
    return any(lp == port and st == LISTEN for lp, _, st, _ in _tcp_table())


def _own_socket_inodes() -> set:
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            out.add(target[8:-1])
    return out


def viewers(grpc_port: int) -> int:
    """Connections to the gRPC port that are not this process's own."""
    table = _tcp_table()
    mine = _own_socket_inodes()
    own_ports = {lp for lp, rp, st, inode in table if rp == grpc_port and inode in mine}
    return sum(1 for lp, rp, st, _ in table if lp == grpc_port and st == ESTABLISHED and rp not in own_ports)


# --------------------------------------------------------------------------
# the mesh side
# --------------------------------------------------------------------------
def open_transport(options: ZenohOptions) -> ZenohTransport:
    """The one place the view opens its zenoh session: ``options`` come from
    the caller (``up --live`` passes an agent's options; with access control
    an identity allowed to subscribe only)."""
    return ZenohTransport(options)


class Watch:
    """A zenoh session subscribed to the run's ticks, reports and stop, feeding
    ``view``; open only while somebody watches."""

    def __init__(self, options: ZenohOptions, keys: Keys, view: LiveView, n: int, m: int, log: Log):
        self.keys, self.view, self.n, self.m, self.log = keys, view, n, m, log
        self.rejected = 0
        self.transport = open_transport(options)
        self.transport.subscribe(keys.tick, self._on_sample)
        self.transport.subscribe(f"{keys.root}/agent/*/report", self._on_sample)
        self.transport.subscribe(keys.stop, self._on_sample)

    def _on_sample(self, key: str, payload: bytes) -> None:
        kind, who = self.keys.parse(key)
        run = self.keys.run_id
        try:
            if kind == "tick":
                self.view.on_tick(wire.decode_tick(payload, run_id=run, agents=len(self.view.ids)))
            elif kind == "report" and who in self.view.index:
                self.view.on_report(wire.decode_report(payload, run_id=run, sender=who, n=self.n, m=self.m))
            elif kind == "stop":
                wire.decode_stop(payload, run_id=run)
                self.view.on_stop()
        except wire.Rejected as e:
            self.rejected += 1
            self.log.once(("rejected", key, e.reason), f"ignored {key}: {e}")

    def close(self) -> None:
        self.transport.close()


def write_status(path: str | None, **status) -> None:
    if not path:
        return
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(status, f)
    os.replace(tmp, path)


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def register(subparsers) -> None:
    p = subparsers.add_parser("live", help="the live view of a mesh run (Rerun's web viewer)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    runspec.add_arguments(p)
    p.add_argument("--ticks", type=positive_int, metavar="K", help="ticks of the run (default: the scenario's steps)")
    p.add_argument("--seed", type=seed_value, default=0, metavar="S", help="the run's seed (default 0)")
    p.add_argument("--port", type=int, default=9090, help="HTTP port of the page (default %(default)s)")
    p.add_argument("--grpc-port", type=int, default=9876, help="port of the data stream (default %(default)s)")
    p.add_argument("--status", metavar="FILE", help="write what went to the view after every poll")
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    spec = runspec.from_args(args)
    scn = spec.load(args.ticks)
    trace = simulate(scn, [args.seed])
    log = Log("live")
    options = zenoh_config.from_args(args)
    keys = Keys(spec.run_id)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # the launcher's stop: clean up below
    home = Path(tempfile.mkdtemp(prefix="diskf-live-"))
    os.environ.update(quiet_rerun_env(home))
    import rerun as rr

    watch = None
    try:
        server = RerunServer(args.port, args.grpc_port, home / "rerun.log")
    except MeshError as e:
        log.error(str(e))
        return 1
    try:
        rec = rr.RecordingStream("diskf-mesh", recording_id=spec.run_id)
        rec.connect_grpc(server.grpc_url, default_blueprint=blueprint())
        sink = RerunSink(rec, scn, trace)
        view = LiveView(scn, trace)
        rec.flush()
        shown, tick, next_poll = 0, 0, 0.0
        while True:
            frame = view.take()
            if frame is not None:
                sink.frame(frame)
                shown, tick = shown + 1, frame.tick
            if time.monotonic() >= next_poll:
                next_poll = time.monotonic() + POLL_S
                v = viewers(args.grpc_port)
                if v and watch is None:
                    watch = Watch(options, keys, view, trace.model.n, trace.model.m, log)
                elif not v and watch is not None:
                    watch.close()
                    watch = None
                write_status(args.status, viewers=v, watching=watch is not None, frames=view.frames, shown=shown,
                             tick=tick, late=view.late)
                if server.proc.poll() is not None:
                    log.error(f"Rerun's server ended (exit code {server.proc.returncode})")
                    return 1
            time.sleep(FRAME_S)
    except MeshError as e:
        log.error(str(e))
        return 1
    finally:
        if watch is not None:
            watch.close()
        server.close()


if __name__ == "__main__":
    from diskf_mesh import cli

    sys.exit(cli.run_one("live", __spec__.name))
