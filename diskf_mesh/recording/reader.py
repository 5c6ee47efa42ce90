"""Reading a recording back, whole, cut short or damaged.

``read(path)`` reads the file's MCAP records in order with the ``mcap``
library's stream reader, every CRC checked (each chunk's, the data
section's), each attachment's CRC and the summary's CRC checked here (the
library reads past them), and stops at the first record that is cut (a world
killed mid-run leaves no summary, no footer, and perhaps half a chunk) or
fails its check: the recording is then readable up to its last closed tick
before that record, and ``Recording.damage`` says why the file is not whole.
Ticks after the last one whose closing record (``/world/tick``) is in the
file are dropped, so every tick a ``Recording`` holds is complete.
"""
from __future__ import annotations

import json
import struct
import zlib
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
_FOOTER, _ATTACHMENT = 0x02, 0x09
_HEAD = struct.Struct("<BQ")
_FOOTER_FIELDS = struct.Struct("<QQ")  # summary start, summary offset start (the summary CRC follows)


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
    damage: str = ""            # why the file is not a whole MCAP file ("" if it is: ``scan``)
    messages_by_topic: dict = field(default_factory=dict)

    @property
    def algorithm(self) -> str:
        return self.run["algorithm"]

    @property
    def planned_ticks(self) -> int:
        return int(self.run["ticks"])

    def not_whole(self) -> str:
        """Why the recording is not the whole run ("" if it is): the file is
        not a whole MCAP file (``damage``), or it lacks the run's result, or
        ticks the run planned."""
        if self.damage:
            return self.damage
        if self.result is None:
            return "it has no result record (the run's end)"
        if self.ticks < self.planned_ticks or int(self.result.get("ticks", -1)) != self.ticks:
            return f"it holds {self.ticks} of the {self.planned_ticks} ticks the run planned"
        return ""


def whole_records(data: bytes) -> tuple:
    """(end of the last whole record before any damage the record walk
    sees, whether the footer and the closing magic are there, why the file
    is not whole so far: "" or a cut record, an attachment or the summary
    failing its CRC) of an MCAP file's bytes."""
    if data[:8] != MAGIC:
        raise ValueError("not an MCAP file (no MCAP magic at its start)")
    pos = 8
    while pos + _HEAD.size <= len(data):
        op, length = _HEAD.unpack_from(data, pos)
        end = pos + _HEAD.size + length
        if end > len(data):
            break
        if op == _ATTACHMENT and length >= 4 and zlib.crc32(data[pos + _HEAD.size:end - 4]) != int.from_bytes(
                data[end - 4:end], "little"):
            return pos, False, f"the attachment at byte {pos} fails its CRC"
        if op == _FOOTER:
            closed = data[end:end + 8] == MAGIC
            return end + 8 * closed, closed, _footer_damage(data, pos, end)
        pos = end
    return pos, False, "it ends inside a record, before its summary and footer: cut short, or a record's length damaged"


def _footer_damage(data: bytes, pos: int, end: int) -> str:
    """Why the footer at ``pos`` (its record ending at ``end``) does not
    close a whole file: "" if the summary is there and its CRC (over the
    summary section and the footer's fields before it) holds, and the
    closing magic follows."""
    if end - pos != _HEAD.size + _FOOTER_FIELDS.size + 4:
        return f"the footer at byte {pos} has the wrong length"
    start, _ = _FOOTER_FIELDS.unpack_from(data, pos + _HEAD.size)
    crc = int.from_bytes(data[end - 4:end], "little")
    if not 8 <= start <= pos:
        return "it has no summary section" if start == 0 else f"the footer points outside the file (byte {start})"
    if crc == 0 or zlib.crc32(data[start:end - 4]) != crc:
        return "the summary fails its CRC" if crc else "the summary carries no CRC"
    if data[end:] != MAGIC:
        return "the closing magic is not the file's last 8 bytes"
    return ""


def scan(data: bytes):
    """Every whole record (chunks opened), in file order, from the ``mcap``
    library's stream reader with its CRC checks, up to the first record that
    is cut or fails a check; then the reason the file is not whole ("" if
    it is: every CRC holds, the data section carries one, and the summary's
    statistics count the messages read). Yields the records, returns the
    reason."""
    from mcap.records import DataEnd, Message, Statistics
    from mcap.stream_reader import StreamReader

    end, _, damage = whole_records(data)
    reader = StreamReader(BytesIO(data[:end]), validate_crcs=True, record_size_limit=len(data))
    messages, counted, data_crc = 0, None, None
    try:
        for rec in reader.records:
            if isinstance(rec, Message):
                messages += 1
            elif isinstance(rec, DataEnd):
                data_crc = rec.data_section_crc
            elif isinstance(rec, Statistics):
                counted = rec.message_count
            yield rec
    except Exception as e:  # noqa: BLE001 - the library's error for a record cut or failing a check: stop there
        return damage or _why(e)
    if damage:
        return damage
    if not data_crc:
        return "its data section carries no CRC"
    if counted != messages:
        return f"its summary counts {counted} messages, the file holds {messages}"
    return ""


def _why(e: Exception) -> str:
    """The damage the stream reader's error ``e`` found, in words."""
    from mcap.exceptions import EndOfFile
    from mcap.stream_reader import CRCValidationError

    if isinstance(e, CRCValidationError):
        return "the data section fails its CRC" if type(e.record).__name__ == "DataEnd" else "a chunk fails its CRC"
    if isinstance(e, EndOfFile):
        return "a record runs past the end of the file"
    if type(e).__name__ == "ZstdError":
        return "a chunk does not decompress"
    return f"a record does not read ({type(e).__name__}: {e})"[:200]


def read(path) -> Recording:
    from mcap.records import Attachment, Channel, Message

    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise InputError("recording", f"cannot read {path}: {e.strerror or e}") from None
    try:
        _, finished, _ = whole_records(data)
    except ValueError as e:
        raise InputError("recording", f"{path}: {e}") from None
    channels, by_topic, trace_doc, segments = {}, {}, None, []
    walk = scan(data)
    while True:
        try:
            rec = next(walk)
        except StopIteration as stop:
            damage = stop.value
            break
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
                                      "its first tick" + (f" ({damage})" if damage else ""))
    return _assemble(str(path), runs[0], join_trace(trace_doc, segments), by_topic, finished, damage)


def _assemble(path: str, run: dict, trace_doc: dict, by_topic: dict, finished: bool, damage: str) -> Recording:
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
                     result=results[-1] if results else None, finished=finished, damage=damage,
                     messages_by_topic=by_topic)


take_ticks = first_ticks  # the first K ticks of a trace (``engine.verify.first_ticks``)
