"""What a recording file holds besides its channels: its format name, and
the run's trace as attachments (``trace.json`` with the first
``SEGMENT_TICKS`` ticks, then a segment per ``SEGMENT_TICKS`` ticks), cut
by the writer (``trace_ticks``) and joined again by the reader
(``join_trace``).
"""
from __future__ import annotations

FORMAT = "diskf-recording/1"
TRACE_ATTACHMENT = "trace.json"  # the trace's fixed part and its first SEGMENT_TICKS ticks
SEGMENT_PREFIX = "trace-ticks-"   # then "trace-ticks-<a>-<b>.json": ticks a+1..b, each attached before tick a+1
SEGMENT_TICKS = 100               # a run stopped at tick k attaches the trace of fewer than k + SEGMENT_TICKS ticks


def trace_ticks(doc: dict, a: int, b: int) -> dict:
    """The per-tick fields of a diskf-trace/1 document for ticks a+1..b."""
    out = {"y": doc["y"][a:b]}
    if doc["links"] and isinstance(doc["links"][0][0], list):  # one matrix per tick
        out["links"] = doc["links"][a:b]
    if "A_seq" in doc:
        out["A_seq"] = doc["A_seq"][a:b]
    if "truth" in doc:
        out["truth"] = {"x": doc["truth"]["x"][a:b], "d": doc["truth"]["d"][a:b]}
    return out


def join_trace(first: dict, segments: list) -> dict:
    """``first`` (the trace.json attachment) with the later segments'
    ticks, in order, as long as they follow on: one diskf-trace/1 document."""
    doc = {**first, "y": list(first["y"])}
    per_tick_links = bool(doc["links"]) and isinstance(doc["links"][0][0], list)
    if per_tick_links:
        doc["links"] = list(doc["links"])
    if "A_seq" in doc:
        doc["A_seq"] = list(doc["A_seq"])
    if "truth" in doc:
        doc["truth"] = {"x": list(doc["truth"]["x"]), "d": list(doc["truth"]["d"])}
    for seg in sorted(segments, key=lambda s: s["from"]):
        if seg["from"] != len(doc["y"]):
            break  # a gap: the ticks after it cannot be read
        doc["y"] += seg["y"]
        if per_tick_links:
            doc["links"] += seg["links"]
        if "A_seq" in doc:
            doc["A_seq"] += seg["A_seq"]
        if "truth" in doc:
            doc["truth"]["x"] += seg["truth"]["x"]
            doc["truth"]["d"] += seg["truth"]["d"]
    return doc
