"""The world's recorder: one MCAP file per run (``world --record``, ``up --record``).

The world calls it at fixed points of its lockstep (``sim.world.World``):

    on_open(k, live)      tick k opened for the agents in ``live``
    on_report(report)     an agent's accepted report of the open tick, with
                          the digest of the agent's own message of the tick
                          as it published it (``wire.Report.sent_digest``)
    on_close(k, missing)  tick k is over: everything of tick k is written,
                          the tick's closing record last; the file is
                          flushed to the OS every ``FLUSH_S``
    finish(status, ...)   the run's result; the MCAP summary and footer

The file is written by a process of its own (``python -m
diskf_mesh.recording.writer``, started by ``Recorder``, niceness ``NICE``):
the world's hooks only hand each closed tick's reports to it as raw bytes
through a pipe (about 10 us a tick; a pipe that is full keeps the frames in
the world until the next tick, so a writer behind never holds up the
lockstep), and the JSON encoding, compression and writing run beside the
run, not under the world's interpreter lock (a writer thread there cost the
run 17 % of its ticks/s). The writer takes the ticks of ``FLUSH_S`` in one
wake-up and then hands the file to the OS. A world killed at any point
(even SIGKILL) closes the pipe; the writer writes what the pipe still holds,
hands it to the OS and leaves a file that is readable up to the last
tick closed (``recording.reader``). Channels and their JSON
Schemas: ``recording.schemas``. The run's trace (model, sensors,
measurements, truth; ``diskf-trace/1``) and estimator settings are attached
as ``trace.json``, written first, so a recording replays on its own.

What each agent sent and did with its neighbours' messages comes from its
reports (``mesh.protocol.verdicts``; a report carries the digest of the agent's own
message as published and of each message it fused, never a message, so
recording adds no message to the wire and no message reaches the world);
a message that a receiver fused with another digest than its sender's is
listed (``differs``). The copies and delays of each message are the
seeded fault layer's plan (``faults.FaultModel``, the same seed and
settings as the agents').

Every CRC MCAP has is written (each chunk's, the data section's, each
attachment's, the summary's), so ``replay`` can tell a whole file from one
cut short or damaged (``recording.reader.scan``).

Messages are stamped with a tick time: log time = recording start +
k x ``TICK_PERIOD_S`` (so a viewer's timeline shows ticks evenly), publish
time = the wall clock when the world closed the tick.
"""
from __future__ import annotations

import json
import math
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import time
from dataclasses import asdict
from importlib import metadata
from pathlib import Path

import numpy as np

from diskf_mesh import __version__
from diskf_mesh.data import provenance
from diskf_mesh.data.outputs import json_safe
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.data.trace import trace_to_json
from diskf_mesh.recording import scene
from diskf_mesh.recording.layout import FORMAT, SEGMENT_PREFIX, SEGMENT_TICKS, TRACE_ATTACHMENT, trace_ticks
from diskf_mesh.recording.schemas import CHANNELS, SCHEMA_PREFIX, schema_bytes

TICK_PERIOD_S = 0.1
CHUNK_BYTES = 1 << 20  # a chunk is also closed at every flush
FLUSH_S = 0.05         # the writer hands the file to the OS at most, and at least, this often
PIPE_BYTES = 1 << 20   # the pipe to the writer holds this much (Linux; a second of ticks of 100 agents)
FINISH_S = 120.0       # after the run, how long the world waits for the writer to close the file
NICE = 10              # the writer's niceness: it yields the cores to the run's processes
_FRAME = struct.Struct("<I")


def versions() -> dict:
    """``provenance.versions()`` and the recording's own libraries."""
    out = provenance.versions()
    for dist in ("mcap", "msgpack"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def _dumps(doc: dict) -> bytes:
    return json.dumps(doc, separators=(",", ":")).encode()


def sent_record(sender, digest: bytes, tick: int, to, differs=()) -> dict:
    """An agent's message as it published it: its digest (``wire.digest``,
    hex); ``to``: the agents it was addressed to, those linked to the sender
    at ``tick``; ``differs``: the receivers that fused a message of this
    sender and tick with another digest (``sender``, ``to`` and
    ``differs`` as the recording names agents)."""
    rec = {"tick": tick, "sender": sender, "to": list(to), "digest": bytes(digest).hex()}
    if differs:
        rec["differs"] = list(differs)
    return rec


class NoRecorder:
    """A run that is not recorded: every hook does nothing."""

    def on_open(self, k, live):
        pass

    def on_report(self, report):
        pass

    def on_close(self, k, missing):
        pass

    def finish(self, status, metrics=None, verification=None):
        """None: nothing failed (``Recorder.finish``)."""
        return None


NO_RECORDER = NoRecorder()


def failure_line(failed: dict) -> str:
    """One line of a recording that failed (``Recorder.finish``'s dict): the
    file, why, and the last tick it holds."""
    held = failed.get("written")
    return (f"recording {failed['path']} failed: {failed['error']}; "
            + ("nothing readable was written" if not held else f"it holds ticks 1 to {held}")
            + f" of {failed['ticks']}")


class Recorder(NoRecorder):
    """The world's side: opens the file (so a bad path fails the command at
    once), starts the writer process on it and feeds it one frame per
    closed tick. Nothing here encodes JSON."""

    def __init__(self, path, trace, scn, *, scenario: str, algorithm: str, seed: int, run_id: str,
                 faults: FaultConfig, provenance: dict | None = None):
        self.path = str(path)
        self._proc = self._spawn()
        self._ticks = int(trace.has.shape[1])
        self._pipe = self._proc.stdin.fileno()
        try:
            import fcntl
            fcntl.fcntl(self._pipe, getattr(fcntl, "F_SETPIPE_SZ", 1031), PIPE_BYTES)
        except (ImportError, OSError):
            pass  # the default pipe (64 kB) then
        os.set_blocking(self._pipe, False)  # a writer behind never holds up a tick: the frames wait here
        self._backlog = bytearray()
        self._failure = None
        self.failed = None              # what ``finish`` found, if writing failed
        self._live = {}                 # k -> live ids
        self._reports = {}              # k -> {agent: wire.Report}
        self._opened_at = None
        self._closed = False
        self._send(("start", {"trace": trace, "scn": scn, "scenario": scenario, "algorithm": algorithm,
                              "seed": int(seed), "run_id": run_id, "faults": faults, "provenance": provenance}),
                   wait=True)

    def _spawn(self) -> subprocess.Popen:
        """The writer process, on the file opened here."""
        Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "wb") as f:
            # its standard output says, at its end, the last tick in the file and what failed (``serve``)
            return subprocess.Popen([sys.executable, "-m", "diskf_mesh.recording.writer", str(f.fileno()),
                                     self.path], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                    pass_fds=(f.fileno(),))

    def _send(self, item, wait: bool = False) -> None:
        """One frame to the writer: what the pipe takes now, the rest at the
        next frame (``wait``: all of it, blocking)."""
        if self._failure is not None:
            return
        data = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
        self._backlog += _FRAME.pack(len(data)) + data
        if wait:
            os.set_blocking(self._pipe, True)
        try:
            while self._backlog:
                del self._backlog[:os.write(self._pipe, self._backlog)]
        except BlockingIOError:
            pass
        except OSError as e:  # the writer is gone (it said why on stderr): the run goes on unrecorded
            self._failure = e
        if wait:
            os.set_blocking(self._pipe, False)

    # -- hooks (the world's lock held) -----------------------------------------
    def on_open(self, k, live):
        self._live[k] = tuple(live)
        if self._opened_at is None:
            self._opened_at = time.monotonic()

    def on_report(self, report):
        self._reports.setdefault(report.tick, {})[report.sender] = report

    def on_close(self, k, missing):
        """Hand tick k to the writer: plain values and the arrays' bytes."""
        if not self._closed:
            wall_s = time.monotonic() - (self._opened_at or time.monotonic())
            reports = [(r.sender, r.x.astype(float, copy=False).tobytes(), r.P.astype(float, copy=False).tobytes(),
                        r.d.astype(float, copy=False).tobytes(), bool(r.d_valid), r.counters, tuple(r.fused),
                        tuple(r.not_fused), bytes(r.sent_digest), tuple(r.digests))
                       for r in self._reports.pop(k, {}).values()]
            self._send(("tick", k, self._live.pop(k, ()), reports, sorted(missing), wall_s, time.time_ns()))

    def finish(self, status, metrics=None, verification=None):
        """The run's result (``status``: "done" or why not; the metrics;
        ``verification``: the run's checked status, ``RunStatus.to_json`` with
        its ``restarts``): the writer adds the MCAP summary and footer and
        closes the file. Returns None, or if writing failed (a full disk, a
        writer that died) {"path", "error", "written": the last tick the
        file holds, "ticks"} (``failure_line``)."""
        if self._closed:
            return self.failed
        self._closed = True
        self._send(("finish", status, json_safe(metrics or {}), json_safe(verification)), wait=True)
        try:
            self._proc.stdin.close()
        except OSError:
            pass
        try:
            self._proc.wait(FINISH_S)  # its one line of standard output fits in the pipe
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        said = self._proc.stdout.read()
        self._proc.stdout.close()
        try:
            end = json.loads(said.decode().strip().splitlines()[-1])
        except (ValueError, IndexError, UnicodeDecodeError):
            end = {"written": None, "error": None}
        if self._proc.returncode != 0 or end.get("error"):
            written = end.get("written")
            if written is None:  # the writer died without a word: what the file holds, read back
                written = _ticks_in(self.path)
            self.failed = {"path": self.path, "written": written, "ticks": self._ticks,
                           "error": end.get("error") or f"the writer ended with status {self._proc.returncode}"}
        return self.failed


def _ticks_in(path: str) -> int:
    """The complete ticks a recording holds (0 if none can be read)."""
    from diskf_mesh.core.errors import InputError
    from diskf_mesh.recording.reader import read

    try:
        return read(path).ticks
    except (InputError, OSError, ValueError):
        return 0


class _Report:
    """A report as the writer gets it (``Recorder.on_close``)."""

    __slots__ = ("sender", "x", "P", "d", "d_valid", "counters", "fused", "not_fused", "sent_digest", "digests")

    def __init__(self, n, m, sender, x, P, d, d_valid, counters, fused, not_fused, sent_digest, digests=()):
        self.sender, self.d_valid, self.counters, self.fused, self.not_fused, self.sent_digest = (
            sender, d_valid, counters, fused, not_fused, sent_digest)
        self.digests = digests
        self.x = np.frombuffer(x, dtype=float)
        self.P = np.frombuffer(P, dtype=float).reshape(n, n)
        self.d = np.frombuffer(d, dtype=float)


class TickWriter:
    """The writer process's side: the MCAP file, one tick at a time."""

    def __init__(self, file, trace, scn, *, scenario: str, algorithm: str, seed: int, run_id: str,
                 faults: FaultConfig, provenance: dict | None = None, mcap=None, scene_each_tick: bool = False):
        """``mcap``: where the messages go instead of an MCAP file on ``file``
        (an object with ``mcap.writer.Writer``'s methods: the live server's
        ``live.server.Sink``); ``scene_each_tick``: write ``/scene`` with
        every tick, not at the end."""
        from mcap.writer import CompressionType, Writer

        self.trace, self.scn, self.seed = trace, scn, int(seed)
        self.scene_each_tick = scene_each_tick
        self.ids = tuple(trace.sensors.ids)
        self.names = dict(zip(self.ids, trace.agent_labels))  # run id -> the user's id
        self.faults = FaultModel(faults, seed) if faults.active else None
        self._file = file
        self._mcap = mcap or Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD,
                                      enable_data_crcs=True)
        self._mcap.start(profile="", library=f"diskf-mesh/{__version__}")
        self._channel = {}
        for topic in CHANNELS:
            sid = self._mcap.register_schema(SCHEMA_PREFIX + topic.strip("/").replace("/", "."), "jsonschema",
                                             schema_bytes(topic))
            self._channel[topic] = self._mcap.register_channel(topic, "json", sid)
        sid = self._mcap.register_schema(*scene.schema())
        self._channel[scene.TOPIC] = self._mcap.register_channel(scene.TOPIC, scene.ENCODING, sid)
        self._mobile = [bool(a.mobile) for a in scn.agents]
        self._colors = {self.names[i]: scene.agent_color(j) for j, i in enumerate(self.ids)}
        extent = max(np.ptp(trace.positions.reshape(-1, 2), axis=0).max(), 1.0)
        self._radius = 0.012 * float(extent)
        self._t0 = time.time_ns()
        self._period = int(TICK_PERIOD_S * 1e9)
        self._last_closed = 0
        self.written = 0                # the last tick handed to the OS whole (a failure leaves the file so)
        self._scenes = []               # per tick, what /scene draws (written at the end)
        K, N = trace.has.shape[1:]
        self.n, self.m = n, m = trace.model.n, trace.model.m
        run = {"format": FORMAT, "run_id": run_id, "scenario": scenario, "scenario_name": scn.name,
               "seed": self.seed, "algorithm": algorithm, "topology": scn.topology,
               "comm_range": scn.comm_range if np.isfinite(scn.comm_range) else "inf",
               "ids": list(trace.agent_labels), "ticks": int(K), "n": int(n), "m": int(m),
               "params": asdict(scn.params), "faults": faults.to_dict(), "tick_period_s": TICK_PERIOD_S,
               "versions": versions(), "provenance": provenance}
        self._put("/run", 0, run)
        self._mcap.flush()  # the channels and /run first
        self._trace_doc = trace_to_json(trace)
        self._trace_doc["params"] = asdict(scn.params)
        self._covered = 0               # the trace's ticks attached so far
        self._attach_through(1)
        self._mcap.add_metadata("run", {k: v if isinstance(v, str) else json.dumps(v) for k, v in run.items()})
        self._file.flush()

    def _time(self, k: int) -> int:
        return self._t0 + k * self._period

    def _attach_through(self, k: int) -> None:
        """Attach the trace's ticks up to at least ``k`` (in segments of
        ``SEGMENT_TICKS``), before any message of tick ``k``: a file cut
        anywhere holds the trace of every tick it closed, and a run stopped
        early carries little of the ticks it never ran."""
        K = len(self._trace_doc["y"])
        while self._covered < min(k, K):
            a, b = self._covered, min(K, self._covered + SEGMENT_TICKS)
            part = trace_ticks(self._trace_doc, a, b)
            if a == 0:
                name, doc = TRACE_ATTACHMENT, {**self._trace_doc, **part}
            else:
                name, doc = f"{SEGMENT_PREFIX}{a}-{b}.json", {"from": a, **part}
            self._mcap.add_attachment(self._t0, self._t0, name, "application/json", _dumps(doc))
            self._covered = b

    def _put(self, topic: str, k: int, doc: dict, now: int | None = None) -> None:
        self._mcap.add_message(self._channel[topic], self._time(k), _dumps(doc), now or time.time_ns())

    def flush(self) -> None:
        """Close the open chunk and hand the file to the OS."""
        self._mcap.flush()
        self._file.flush()
        self.written = self._last_closed

    def write_tick(self, k, live, reports, missing, wall_s, now) -> None:
        """Every channel of closed tick ``k``, ``/world/tick`` last.
        ``reports``: ``Recorder.on_close``'s tuples."""
        self._attach_through(k)
        tr, ids, name = self.trace, self.ids, self.names
        reports = {r[0]: _Report(self.n, self.m, *r) for r in reports}
        alive = set(live)
        links = tr.links[0, k - 1]
        truth_x = tr.truth_x[0, k - 1]
        dims = list(tr.position_dims)
        put = lambda topic, doc: self._put(topic, k, doc, now)  # noqa: E731
        names = lambda seq: [name.get(i, i) for i in seq]  # noqa: E731
        put("/world/truth", {"tick": k, "x": truth_x.tolist(), "d": tr.truth_d[0, k - 1].tolist(),
                             "position": truth_x[dims].tolist()})
        put("/world/agents", {"tick": k, "ids": list(tr.agent_labels), "positions": tr.positions[k - 1].tolist(),
                              "live": names(live)})
        N = len(ids)
        edges = [[name[ids[i // N]], name[ids[i % N]]]
                 for i in np.flatnonzero(np.triu(links, 1).ravel()).tolist()
                 if ids[i // N] in alive and ids[i % N] in alive]
        put("/world/links", {"tick": k, "edges": edges})
        order = lambda i: ids.index(i) if i in ids else N  # noqa: E731
        fused_as = {}  # sender -> {receiver: the digest it fused}
        for r in reports.values():
            for s, g in zip(r.fused, r.digests):
                fused_as.setdefault(s, {})[r.sender] = bytes(g)
        put("/agents/sent", {"tick": k, "messages": [
            sent_record(name[r.sender], r.sent_digest, k,
                        names(sorted({s for s in r.fused} | {s for s, _ in r.not_fused}, key=order)),
                        names(sorted((i for i, g in fused_as.get(r.sender, {}).items() if g != r.sent_digest),
                                     key=order)))
            for r in (reports[i] for i in ids if i in reports) if r.sent_digest]})
        estimates, counters, deliveries = [], [], []
        for j, i in enumerate(ids):
            r = reports.get(i)
            if r is not None:
                x = r.x.tolist()
                err = math.dist([x[a] for a in dims], truth_x[dims].tolist())
                estimates.append({"agent": name[i], "x": x, "P": r.P.tolist(),
                                  "d": r.d.tolist() if r.d_valid else None, "d_valid": bool(r.d_valid),
                                  "fused": names(r.fused), "digests": [bytes(g).hex() for g in r.digests],
                                  "position_error": err})
                counters.append({"agent": name[i], "counters": r.counters})
                verdicts = [(s, "fused") for s in r.fused] + list(r.not_fused)
            elif i in alive:
                verdicts = [(s, "unreported") for s, ln in zip(ids, links[j].tolist()) if ln and s != i and s in alive]
            else:
                continue
            for s, v in sorted(verdicts, key=lambda e: order(e[0])):
                verdict, _, reason = v.partition(":")
                doc = {"sender": name.get(s, s), "receiver": name[i], "verdict": verdict}
                if reason:
                    doc["reason"] = reason
                if self.faults is not None:
                    plan = self.faults.plan(s, i, k)
                    doc["copies"], doc["delays_ms"] = len(plan), [1e3 * d.delay_s for d in plan]
                else:
                    doc["copies"], doc["delays_ms"] = 1, [0.0]
                deliveries.append(doc)
        put("/agents/delivered", {"tick": k, "deliveries": deliveries})
        put("/agents/estimates", {"tick": k, "estimates": estimates})
        put("/agents/counters", {"tick": k, "counters": counters})
        self._scenes.append((k, {name[i] for i in alive if i in name}, edges,
                             [(e["agent"], e["x"], e["P"]) for e in estimates]))
        if self.scene_each_tick:
            self._write_scenes()
        put("/world/tick", {"tick": k, "reported": names(sorted(reports, key=order)), "missing": names(missing),
                            "wall_s": wall_s})
        self._last_closed = k

    def _write_scenes(self) -> None:
        """``/scene`` of every closed tick. Written once the ticks are over (it
        is most of a tick's bytes, and only a viewer needs it), so a run
        killed before its end has every channel but this one."""
        tr, dims = self.trace, list(self.trace.position_dims)[:2]
        for k, alive, edges, estimates in self._scenes:
            update = scene.scene_update(
                k, self._time(k), tr.agent_labels, tr.positions[k - 1], self._mobile, alive, edges,
                tr.truth_x[0, max(k - scene.TRAIL, 0):k][:, dims],
                [(i, [x[a] for a in dims], [[P[a][b] for b in dims] for a in dims]) for i, x, P in estimates],
                self._colors, self._radius)
            self._mcap.add_message(self._channel[scene.TOPIC], self._time(k), update.encode(), time.time_ns())
        self._scenes = []

    def finish(self, status, metrics, verification=None) -> None:
        """``/scene``, the run's result, the MCAP summary and footer."""
        k = self._last_closed
        self._write_scenes()
        doc = {"status": status, "ticks": k, "metrics": metrics}
        if verification:
            doc["verification"] = verification
        self._put("/run/result", k, doc)
        self._mcap.finish()


def _frames(buf: bytearray):
    """Every whole frame at the start of ``buf`` (taken out of it)."""
    while len(buf) >= _FRAME.size:
        size, = _FRAME.unpack_from(buf)
        if len(buf) < _FRAME.size + size:
            return
        data = bytes(buf[_FRAME.size:_FRAME.size + size])
        del buf[:_FRAME.size + size]
        yield pickle.loads(data)


def serve(fd: int, path: str, pipe: int = 0) -> int:
    """The writer process: frames from ``pipe`` (``Recorder``) into the MCAP
    file open on ``fd``, until the world's finish frame or the pipe's end
    (the world was killed: what is written is handed to the OS, no footer).
    The file goes to the OS once the frames waiting are written, at most and
    at least every ``FLUSH_S``. A failed write (a full disk) stops the
    recording, never the run: the pipe is drained to its end. Its last act
    is one JSON line on standard output, ``{"written": the last tick the
    file holds, "error": why writing failed or null}``; exit status 1 if it
    failed."""
    for sig in (signal.SIGINT, signal.SIGTERM):  # a Ctrl-C or a stop of the group is the world's to handle:
        signal.signal(sig, signal.SIG_IGN)       # it finishes the file, or its end closes the pipe
    try:
        os.nice(NICE)  # the lockstep's processes first; the pipe and the backlog absorb the lag
    except OSError:
        pass
    file = os.fdopen(fd, "wb")
    writer, failure, buf = None, None, bytearray()
    unflushed, flush_due, written, finished = False, 0.0, 0, 0
    while True:
        wait = max(flush_due - time.monotonic(), 0.0) if unflushed else None
        ready, _, _ = select.select([pipe], [], [], wait)
        chunk = os.read(pipe, PIPE_BYTES) if ready else b""
        if ready and not chunk:
            break
        buf += chunk
        try:
            for item in _frames(buf):
                if failure is not None:
                    continue
                if item[0] == "start":
                    writer = TickWriter(file, **item[1])
                elif item[0] == "tick":
                    writer.write_tick(*item[1:])
                    unflushed = True
                elif item[0] == "finish":
                    writer.finish(*item[1:])
                    unflushed, writer, finished = False, None, writer._last_closed
            if unflushed and time.monotonic() >= flush_due:
                writer.flush()
                unflushed, flush_due = False, time.monotonic() + FLUSH_S
            elif unflushed:  # the ticks of the next FLUSH_S come in one wake-up, not one each
                time.sleep(max(flush_due - time.monotonic(), 0.0))
        except Exception as e:  # noqa: BLE001 - a failed write stops the recording, not the run
            if failure is None:
                failure, written = e, (writer.written if writer is not None else 0)
    if writer is not None and failure is None and unflushed:
        try:
            writer.flush()
        except Exception as e:  # noqa: BLE001
            failure, written = e, writer.written
    if failure is None:
        written = writer.written if writer is not None else finished
    try:
        file.close()
    except OSError as e:
        if failure is None:
            failure = e
    why = None if failure is None else (getattr(failure, "strerror", None) or f"{type(failure).__name__}: {failure}")
    try:
        os.write(1, (json.dumps({"written": written, "error": why}) + "\n").encode())
    except OSError:
        pass
    return 0 if failure is None else 1


if __name__ == "__main__":
    sys.exit(serve(int(sys.argv[1]), sys.argv[2]))
