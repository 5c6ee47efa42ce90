"""The world's recorder: one MCAP file per run (``world --record``, ``up --record``).

The world calls it at fixed points of its lockstep (``sim.world.World``):

    on_open(k, live)      tick k opened for the agents in ``live``
    on_report(report)     an agent's accepted report of the open tick, with
                          the agent's own message of the tick as it published
                          it (``wire.Report.sent``)
    on_close(k, missing)  tick k is over: everything of tick k is written,
                          the tick's closing record last; the file is
                          flushed to the OS every ``FLUSH_S`` (and at the
                          last tick)
    finish(status, ...)   the run's result; the MCAP summary and footer

so a world killed at any point (even SIGKILL) leaves a file that is readable
up to the last tick closed before its last flush (``recording.reader``). Channels and their JSON
Schemas: ``recording.schemas``. The run's trace (model, sensors,
measurements, truth; ``diskf-trace/1``) and estimator settings are attached
as ``trace.json``, written first, so a recording replays on its own.

What each agent sent and did with its neighbours' messages comes from its
reports (``recording.verdicts``; the report carries the agent's own message
as published, so recording adds no message to the wire); the copies and delays of each message are the
seeded fault layer's plan (``faults.FaultModel``, the same seed and
settings as the agents').

Messages are stamped with a tick time: log time = recording start +
k x ``TICK_PERIOD_S`` (so a viewer's timeline shows ticks evenly), publish
time = the wall clock when the world wrote it.
"""
from __future__ import annotations

import json
import math
import platform
import queue
import struct
import sys
import threading
import time
from dataclasses import asdict
from importlib import metadata
from pathlib import Path

import msgpack
import numpy as np

from diskf_mesh import __version__
from diskf_mesh.data.outputs import json_safe
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.data.trace import trace_to_json
from diskf_mesh.recording import scene
from diskf_mesh.recording.schemas import CHANNELS, SCHEMA_PREFIX, schema_bytes

FORMAT = "diskf-recording/1"
TICK_PERIOD_S = 0.1
TRACE_ATTACHMENT = "trace.json"
CHUNK_BYTES = 1 << 20  # a chunk is also closed at every flush
FLUSH_S = 0.05         # the writer thread hands the file to the OS at most, and at least, this often


def versions() -> dict:
    out = {"diskf-mesh": __version__, "python": platform.python_version()}
    for dist in ("numpy", "eclipse-zenoh", "mcap", "msgpack"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "absent"
    return out


def _dumps(doc: dict) -> bytes:
    return json.dumps(doc, separators=(",", ":")).encode()


def sent_record(sender: int, payload: bytes, tick: int, to) -> dict:
    """An agent's message as it published it, decoded without the guard's
    checks (the record says what was sent); ``to``: the agents it was
    addressed to, those linked to the sender at ``tick``."""
    rec = {"tick": tick, "sender": sender, "to": list(to), "bytes": len(payload)}
    try:
        doc = msgpack.unpackb(payload, raw=False)
        n, m, blob = doc["n"], doc["m"], doc["a"]
        a = struct.unpack(f"<{len(blob) // 8}d", blob)
        sizes = (n, n * n, n, n * n, m, m * m)
        if len(a) != sum(sizes):
            raise ValueError("arrays of the wrong size")
        parts, i = [], 0
        for size in sizes:
            parts.append(list(a[i:i + size]))
            i += size
        rows = lambda v, k: [v[r * k:(r + 1) * k] for r in range(k)]  # noqa: E731
        rec.update(x_pred=parts[0], P_pred=rows(parts[1], n), x_upd=parts[2], P_upd=rows(parts[3], n),
                   d=parts[4], S=rows(parts[5], m), d_valid=bool(doc.get("dv")))
    except Exception as e:  # noqa: BLE001 - anything on the wire is recorded, readable or not
        rec["undecodable"] = f"{type(e).__name__}: {e}"[:200]
    return rec


class NoRecorder:
    """A run that is not recorded: every hook does nothing."""

    def on_open(self, k, live):
        pass

    def on_report(self, report):
        pass

    def on_close(self, k, missing):
        pass

    def finish(self, status, metrics=None):
        pass


NO_RECORDER = NoRecorder()


class Recorder(NoRecorder):
    def __init__(self, path, trace, scn, *, scenario: str, algorithm: str, seed: int, run_id: str,
                 faults: FaultConfig):
        from mcap.writer import CompressionType, Writer

        self.path = str(path)
        self.trace, self.scn, self.seed = trace, scn, int(seed)
        self.ids = tuple(trace.sensors.ids)
        self.faults = FaultModel(faults, seed) if faults.active else None
        Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._mcap = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._mcap.start(profile="", library=f"diskf-mesh/{__version__}")
        self._channel = {}
        for topic in CHANNELS:
            sid = self._mcap.register_schema(SCHEMA_PREFIX + topic.strip("/").replace("/", "."), "jsonschema",
                                             schema_bytes(topic))
            self._channel[topic] = self._mcap.register_channel(topic, "json", sid)
        sid = self._mcap.register_schema(scene.NAME, "jsonschema", json.dumps(scene.SCHEMA).encode())
        self._channel[scene.TOPIC] = self._mcap.register_channel(scene.TOPIC, "json", sid)
        self._mobile = [bool(a.mobile) for a in scn.agents]
        self._colors = {i: scene.agent_color(j) for j, i in enumerate(self.ids)}
        extent = max(np.ptp(trace.positions.reshape(-1, 2), axis=0).max(), 1.0)
        self._radius = 0.012 * float(extent)
        self._t0 = time.time_ns()
        self._period = int(TICK_PERIOD_S * 1e9)
        self._open = 0
        self._opened_at = None
        self._live = {}                 # k -> live ids
        self._reports = {}              # k -> {agent: wire.Report}
        self._closed = False
        self._last_closed = 0
        self._flush_due = 0.0
        self._scenes = []               # per tick, what /scene draws (written at the end)
        K, N = trace.has.shape[1:]
        n, m = trace.model.n, trace.model.m
        run = {"format": FORMAT, "run_id": run_id, "scenario": scenario, "scenario_name": scn.name,
               "seed": self.seed, "algorithm": algorithm, "topology": scn.topology,
               "comm_range": scn.comm_range if np.isfinite(scn.comm_range) else "inf",
               "ids": list(self.ids), "ticks": int(K), "n": int(n), "m": int(m), "params": asdict(scn.params),
               "faults": faults.to_dict(), "tick_period_s": TICK_PERIOD_S, "versions": versions()}
        self._put("/run", 0, run)
        self._mcap.flush()  # the channels and /run first
        doc = trace_to_json(trace)
        doc["params"] = asdict(scn.params)
        self._mcap.add_attachment(self._t0, self._t0, TRACE_ATTACHMENT, "application/json", _dumps(doc))
        self._mcap.add_metadata("run", {k: v if isinstance(v, str) else json.dumps(v) for k, v in run.items()})
        self._file.flush()
        self._queue = queue.SimpleQueue()  # closed ticks, for the writer thread
        self._failure = None
        self._thread = threading.Thread(target=self._write_ticks, name="recorder", daemon=True)
        self._thread.start()

    def _time(self, k: int) -> int:
        return self._t0 + k * self._period

    def _put(self, topic: str, k: int, doc: dict, now: int | None = None) -> None:
        self._mcap.add_message(self._channel[topic], self._time(k), _dumps(doc), now or time.time_ns())

    # -- hooks (the world's lock held) -----------------------------------------
    def on_open(self, k, live):
        self._open = k
        self._live[k] = tuple(live)
        if self._opened_at is None:
            self._opened_at = time.monotonic()

    def on_report(self, report):
        self._reports.setdefault(report.tick, {})[report.sender] = report

    def on_close(self, k, missing):
        """Hand tick k to the writer thread: the lockstep opens the next tick
        at once, and the tick is written while the agents work on it."""
        if not self._closed:
            wall_s = time.monotonic() - (self._opened_at or time.monotonic())
            self._queue.put((k, self._live.pop(k, ()), self._reports.pop(k, {}), sorted(missing), wall_s,
                             time.time_ns()))

    def _write_ticks(self) -> None:
        """The writer thread: every closed tick in turn; the file goes to the
        OS once the thread has caught up (at most every ``FLUSH_S``), and at
        least every ``FLUSH_S`` while something is unflushed."""
        unflushed = False
        while True:
            try:
                item = self._queue.get(timeout=FLUSH_S)
            except queue.Empty:
                item = ()
            if item is None:
                return
            try:
                if item and self._failure is None:
                    self._write_tick(*item)
                    unflushed = True
                if unflushed and self._queue.empty() and time.monotonic() >= self._flush_due:
                    self._mcap.flush()
                    self._flush_due, unflushed = time.monotonic() + FLUSH_S, False
            except Exception as e:  # noqa: BLE001 - a failed write stops the recording, not the run
                self._failure = self._failure or e

    def _write_tick(self, k, live, reports, missing, wall_s, now) -> None:
        tr, ids = self.trace, self.ids
        alive = set(live)
        links = tr.links[0, k - 1]
        truth_x = tr.truth_x[0, k - 1]
        dims = list(tr.position_dims)
        put = lambda topic, doc: self._put(topic, k, doc, now)  # noqa: E731
        put("/world/truth", {"tick": k, "x": truth_x.tolist(), "d": tr.truth_d[0, k - 1].tolist(),
                             "position": truth_x[dims].tolist()})
        put("/world/agents", {"tick": k, "ids": list(ids), "positions": tr.positions[k - 1].tolist(),
                              "live": list(live)})
        N = len(ids)
        edges = [[ids[i // N], ids[i % N]] for i in np.flatnonzero(np.triu(links, 1).ravel()).tolist()
                 if ids[i // N] in alive and ids[i % N] in alive]
        put("/world/links", {"tick": k, "edges": edges})
        order = lambda i: ids.index(i) if i in ids else N  # noqa: E731
        put("/agents/sent", {"tick": k, "messages": [
            sent_record(r.sender, r.sent, k, sorted({s for s in r.fused} | {s for s, _ in r.not_fused}, key=order))
            for r in (reports[i] for i in ids if i in reports) if r.sent]})
        estimates, counters, deliveries = [], [], []
        for j, i in enumerate(ids):
            r = reports.get(i)
            if r is not None:
                x = r.x.tolist()
                err = math.dist([x[a] for a in dims], truth_x[dims].tolist())
                estimates.append({"agent": i, "x": x, "P": r.P.tolist(), "d": r.d.tolist() if r.d_valid else None,
                                  "d_valid": bool(r.d_valid), "fused": list(r.fused), "position_error": err})
                counters.append({"agent": i, "counters": r.counters})
                verdicts = [(s, "fused") for s in r.fused] + list(r.not_fused)
            elif i in alive:
                verdicts = [(s, "unreported") for s, ln in zip(ids, links[j].tolist()) if ln and s != i and s in alive]
            else:
                continue
            for s, v in sorted(verdicts, key=lambda e: ids.index(e[0]) if e[0] in ids else N):
                verdict, _, reason = v.partition(":")
                doc = {"sender": s, "receiver": i, "verdict": verdict}
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
        self._scenes.append((k, alive, edges, [(e["agent"], e["x"], e["P"]) for e in estimates]))
        put("/world/tick", {"tick": k, "reported": sorted(reports, key=ids.index), "missing": missing,
                            "wall_s": wall_s})
        self._last_closed = k

    def _write_scenes(self) -> None:
        """``/scene`` of every closed tick. Written once the ticks are over (it
        is most of a tick's bytes, and only a viewer needs it), so a run
        killed before its end has every channel but this one."""
        tr, dims = self.trace, list(self.trace.position_dims)[:2]
        for k, alive, edges, estimates in self._scenes:
            self._put(scene.TOPIC, k, scene.scene_update(
                k, self._time(k), self.ids, tr.positions[k - 1], self._mobile, alive, edges,
                tr.truth_x[0, max(k - scene.TRAIL, 0):k][:, dims],
                [(i, [x[a] for a in dims], [[P[a][b] for b in dims] for a in dims]) for i, x, P in estimates],
                self._colors, self._radius))
        self._scenes = []

    def finish(self, status, metrics=None):
        """The run's result (``status``: "done" or why not; the metrics),
        then the MCAP summary and footer; the file is closed. If writing it
        failed, one line ``warning: ...`` on stderr (the run is not
        affected)."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        if self._failure is None:
            k = self._last_closed
            self._write_scenes()
            self._put("/run/result", k, {"status": status, "ticks": k, "metrics": json_safe(metrics or {})})
            self._mcap.finish()
        self._file.close()
        if self._failure is not None:
            print(f"warning: recording {self.path} stopped at tick {self._last_closed}: {self._failure}",
                  file=sys.stderr)
