"""Reading a recording back, whole or cut short.

``read(path)`` reads every complete MCAP record of the file and stops at the
first one the end of the file cuts (a world killed mid-run leaves no
summary, no footer, and perhaps half a chunk): the recording is then
readable up to its last closed tick. Ticks after the last one whose closing
record (``/world/tick``) is in the file are dropped, so every tick a
``Recording`` holds is complete.
"""
from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path

import numpy as np

from diskf_mesh.core.errors import InputError
from diskf_mesh.estimators import Params
from diskf_mesh.data.trace import Trace, estimator_from_json, trace_from_json
from diskf_mesh.engine.verify import first_ticks
from diskf_mesh.mesh.protocol.reports import RunReports
from diskf_mesh.recording.layout import FORMAT, SEGMENT_PREFIX, TRACE_ATTACHMENT, join_trace

MAGIC = b"\x89MCAP0\r\n"
_FOOTER = 0x02
_HEAD = struct.Struct("<BQ")


@dataclass
class Recording(RunReports):
    """A recording's complete ticks 1..K: what the reports said
    (``RunReports``: x, P, d, d_valid, reported, and fused with the diagonal
    True), and the rest of the file."""

    path: str = ""
    run: dict = field(default_factory=dict)  # the /run message
    trace: Trace | None = None  # the whole run's trace (all planned ticks)
    params: Params | None = None
    ticks: int = 0              # complete ticks K
    ids: tuple = ()
    sent: list = field(default_factory=list)        # every message sent at ticks <= K (/agents/sent)
    delivered: list = field(default_factory=list)   # every delivery of ticks <= K, with its tick
    counters: dict = field(default_factory=dict)    # (k, agent) -> counters
    positions: np.ndarray | None = None             # (K, N, 2)
    edges: list = field(default_factory=list)       # per tick, [[a, b], ...]
    live: np.ndarray | None = None              # (K, N) the live set of each tick
    result: dict | None = None  # /run/result, when the run ended and wrote it
    finished: bool = False      # the file has its footer (the world closed it)
    messages_by_topic: dict = field(default_factory=dict)

    @property
    def algorithm(self) -> str:
        return self.run["algorithm"]

    @property
    def planned_ticks(self) -> int:
        return int(self.run["ticks"])


def whole_records(data: bytes) -> tuple:
    """(end of the last whole record, whether the footer and the closing
    magic are there) of an MCAP file's bytes."""
    if data[:8] != MAGIC:
        raise ValueError("not an MCAP file (no MCAP magic at its start)")
    pos = 8
    while pos + _HEAD.size <= len(data):
        op, length = _HEAD.unpack_from(data, pos)
        end = pos + _HEAD.size + length
        if end > len(data):
            break
        pos = end
        if op == _FOOTER:
            return pos, data[pos:pos + 8] == MAGIC
    return pos, False


def records(data: bytes):
    """Every whole record (chunks opened), in file order; stops quietly at
    a record the file cuts or a chunk that does not decompress."""
    from mcap.stream_reader import StreamReader

    end, _ = whole_records(data)
    reader = StreamReader(BytesIO(data[8:end]), skip_magic=True)
    it = reader.records
    while True:
        try:
            rec = next(it)
        except StopIteration:
            return
        except Exception:  # noqa: BLE001 - a damaged tail (bad CRC, undecompressable chunk): stop there
            return
        yield rec


def read(path) -> Recording:
    from mcap.records import Attachment, Channel, Message

    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise InputError("recording", f"cannot read {path}: {e.strerror or e}") from None
    try:
        _, finished = whole_records(data)
    except ValueError as e:
        raise InputError("recording", f"{path}: {e}") from None
    channels, by_topic, trace_doc, segments = {}, {}, None, []
    for rec in records(data):
        if isinstance(rec, Channel):
            channels[rec.id] = (rec.topic, rec.message_encoding == "json")
        elif isinstance(rec, Message) and rec.channel_id in channels:
            topic, is_json = channels[rec.channel_id]
            try:  # a channel in another encoding (``/scene``: protobuf) keeps its bytes
                by_topic.setdefault(topic, []).append(json.loads(rec.data) if is_json else bytes(rec.data))
            except ValueError:
                continue
        elif isinstance(rec, Attachment) and rec.name == TRACE_ATTACHMENT:
            trace_doc = json.loads(rec.data)
        elif isinstance(rec, Attachment) and rec.name.startswith(SEGMENT_PREFIX):
            segments.append(json.loads(rec.data))
    runs = by_topic.get("/run", [])
    if not runs or runs[0].get("format") != FORMAT or trace_doc is None:
        raise InputError("recording", f"{path} is not a diskf-mesh recording ({FORMAT}) or was cut before "
                                      "its first tick")
    return _assemble(str(path), runs[0], join_trace(trace_doc, segments), by_topic, finished)


def _assemble(path: str, run: dict, trace_doc: dict, by_topic: dict, finished: bool) -> Recording:
    params = estimator_from_json({"estimator": trace_doc.pop("params", {})})  # diskf-r's switches too
    trace = trace_from_json(trace_doc)
    ids = tuple(run["ids"])
    N, n, m = len(ids), int(run["n"]), int(run["m"])
    closed = {doc["tick"] for doc in by_topic.get("/world/tick", [])}
    K = 0
    while K + 1 in closed and K < trace.shape[1]:
        K += 1
    where = {i: j for j, i in enumerate(ids)}
    reports = RunReports(**RunReports.empty(K, N, n, m))
    x, P, d, d_valid, reported, fused = (reports.x, reports.P, reports.d, reports.d_valid, reports.reported,
                                         reports.fused)
    in_run = lambda topic: [doc for doc in by_topic.get(topic, []) if 1 <= doc["tick"] <= K]  # noqa: E731
    delivered = [{"tick": doc["tick"], **e} for doc in in_run("/agents/delivered") for e in doc["deliveries"]]
    said = {}
    for e in delivered:
        if e["verdict"] != "fused" and e["receiver"] in where:
            said.setdefault((e["tick"], e["receiver"]), []).append(
                (e["sender"], e["verdict"] + (f":{e['reason']}" if e.get("reason") else "")))
    for doc in in_run("/agents/estimates"):
        k = doc["tick"]
        for e in doc["estimates"]:
            j = where.get(e["agent"])
            if j is None:
                continue
            x[k - 1, j], P[k - 1, j] = e["x"], e["P"]
            d_valid[k - 1, j] = e["d_valid"]
            if e["d"] is not None:
                d[k - 1, j] = e["d"]
            reported[k - 1, j] = True
            reports.note_fused(k, j, e["fused"], said.get((k, e["agent"]), ()),
                               [bytes.fromhex(g) for g in e.get("digests", ())], where)
    fused[:, np.arange(N), np.arange(N)] = True
    positions = np.full((K, N, 2), np.nan)
    live = np.zeros((K, N), dtype=bool)
    edges = [[] for _ in range(K)]
    for doc in in_run("/world/agents"):
        positions[doc["tick"] - 1] = doc["positions"]
        for i in doc.get("live", ()):
            if i in where:
                live[doc["tick"] - 1, where[i]] = True
    if not any("live" in doc for doc in in_run("/world/agents")):
        live = None  # not recorded: every agent counts as live
    for doc in in_run("/world/links"):
        edges[doc["tick"] - 1] = doc["edges"]
    counters = {(doc["tick"], c["agent"]): c["counters"] for doc in in_run("/agents/counters") for c in doc["counters"]}
    sent = [m for doc in by_topic.get("/agents/sent", []) for m in doc["messages"] if 1 <= m["tick"] <= K]
    results = by_topic.get("/run/result", [])
    fields_ = {f: getattr(reports, f) for f in ("x", "P", "d", "d_valid", "reported", "fused", "digests", "verdicts")}
    return Recording(**fields_, live=live, path=path, run=run, trace=trace, params=params, ticks=K, ids=ids, sent=sent,
                     delivered=delivered, counters=counters, positions=positions, edges=edges,
                     result=results[-1] if results else None, finished=finished, messages_by_topic=by_topic)


take_ticks = first_ticks  # the first K ticks of a trace (``engine.verify.first_ticks``)
