"""Where one mesh process's time goes, phase by phase (``--profile DIR``).

A mesh process does its work in the transport's callbacks (zenoh's network
threads) and, for timeouts and start-up, in its main thread. ``Phases``
measures both the same way:

* work: code between ``phases.begin()`` and ``phases.end("decode")`` counts
  for that phase, in wall time (``time.perf_counter``) and in the CPU time
  of the thread that ran it (``time.thread_time``). Spans nest (per
  thread): a span's own figure leaves out the spans inside it; an outermost
  span that is not split further is "other" (range gate, inbox,
  bookkeeping, the transport's hand-over).
* waiting: wall time during which no span runs on any thread goes to the
  wait phase the process declared with ``phases.waiting = "wait-world"``
  (an agent waits for the world's tick, then for its neighbours).

So the phases add up to the process's wall time between ``start()`` and
``stop()``, but for spans of two threads at once (two of zenoh's callback
threads), whose overlap counts in both. ``process_cpu`` (``time.process_time``) covers every thread,
zenoh's own (Rust) work included: the difference to the spans' CPU is what
zenoh and the kernel spend outside Python.

``NO_PHASES`` does nothing, for runs without ``--profile``: every call is an
empty method. ``summary()`` is the JSON a process writes at exit; ``merge``
averages several, ``format_table`` prints one.

Agent phases (``AGENT_PHASES``)::

    wait-world       waiting for the world's tick k and own measurement
    wait-neighbours  after publishing, waiting for the neighbours' messages
    decode           unpacking payloads (world's tick, measurement, messages)
    guard            the guard's numerical checks of a neighbour's message
    local            the local step (math)
    fuse             the fusion step (math)
    encode           packing the own message and the report
    publish          handing them to zenoh (``put``)
    other            the rest of the callbacks: routing, range gate, inbox

World phases (``WORLD_PHASES``): wait-reports, decode, check (the online check), wait-check (the world
blocked on the check's thread), encode, publish, other. The check's thread works beside the world's
callbacks: its spans are ``begin(beside=True)``, which count their CPU time in their phase and no wall
time (it overlaps the world's own), so the wall column still adds up to the process's wall time and the
world's waiting for the check is its own phase.
"""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path

AGENT_PHASES = ("wait-world", "wait-neighbours", "decode", "guard", "local", "fuse", "encode", "publish", "other")
WORLD_PHASES = ("wait-reports", "decode", "check", "wait-check", "encode", "publish", "other")
FORMAT = "diskf-mesh-profile/2"


class Phases:
    def __init__(self, names, who: str = "", wall=time.perf_counter, cpu=time.thread_time,
                 process_cpu=time.process_time):
        self.names = tuple(names)
        self.who = who
        self._wall, self._cpu, self._process_cpu = wall, cpu, process_cpu
        self._lock = threading.Lock()
        self._local = threading.local()
        self.start()

    def start(self) -> None:
        """(Re)start the measurement: every figure from zero."""
        with self._lock:
            self.wall = dict.fromkeys(self.names, 0.0)
            self.cpu = dict.fromkeys(self.names, 0.0)
            self.ticks = 0
            self.waiting = self.names[0]
            self._active = 0
            self._t0 = self._idle_since = self._wall()
            self._p0 = self._process_cpu()
            self._elapsed = self._process = None

    def begin(self, beside: bool = False) -> None:
        """A span of work starts on this thread (close it with ``end``);
        ``beside``: on a thread that works beside the process's own (its
        CPU time counts, its wall time overlaps theirs and does not)."""
        stack = self._local.__dict__.setdefault("stack", [])
        now = self._wall()
        if not stack and not beside:
            with self._lock:
                if not self._active:
                    self.wall[self.waiting] += now - self._idle_since
                self._active += 1
        stack.append([now, self._cpu(), 0.0, 0.0, beside])

    def end(self, phase: str = "other") -> None:
        """The innermost open span of this thread ends; it was ``phase``."""
        stack = self._local.stack
        w0, c0, nested_w, nested_c, beside = stack.pop()
        now = self._wall()
        w, c = now - w0, self._cpu() - c0
        with self._lock:
            if not beside:
                self.wall[phase] += w - nested_w
            self.cpu[phase] += c - nested_c
            if not stack and not beside:
                self._active -= 1
                if not self._active:
                    self._idle_since = now
        if stack:
            stack[-1][2] += w
            stack[-1][3] += c

    def tick(self) -> None:
        self.ticks += 1

    def stop(self) -> None:
        with self._lock:
            now = self._wall()
            if not self._active:
                self.wall[self.waiting] += now - self._idle_since
                self._idle_since = now
            self._elapsed = now - self._t0
            self._process = self._process_cpu() - self._p0

    def summary(self) -> dict:
        """Seconds per phase over the whole measurement, and per tick."""
        if self._elapsed is None:
            self.stop()
        k = max(self.ticks, 1)
        return {
            "format": FORMAT, "who": self.who, "ticks": self.ticks, "elapsed_s": self._elapsed,
            "process_cpu_s": self._process, "python_cpu_s": sum(self.cpu.values()),
            "phases": {p: {"wall_ms_per_tick": 1e3 * self.wall[p] / k, "cpu_ms_per_tick": 1e3 * self.cpu[p] / k}
                       for p in self.names},
        }

    def write(self, directory, name: str) -> Path:
        path = Path(directory) / f"{name}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.summary(), indent=1))
        return path


class _NoPhases:
    """``Phases`` that measures nothing (no ``--profile``)."""

    @property
    def waiting(self) -> str:
        return ""

    @waiting.setter
    def waiting(self, phase: str) -> None:
        pass

    def start(self) -> None:
        pass

    def begin(self, beside: bool = False) -> None:
        pass

    def end(self, phase: str = "other") -> None:
        pass

    def tick(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def __bool__(self) -> bool:
        return False


NO_PHASES = _NoPhases()


def merge(summaries) -> dict:
    """Mean per-tick figures over several processes' summaries (e.g. every agent)."""
    summaries = list(summaries)
    if not summaries:
        return {}
    n = len(summaries)
    per_tick = lambda s, key: 1e3 * s[key] / max(s["ticks"], 1)  # noqa: E731
    return {
        "processes": n,
        "ticks": min(s["ticks"] for s in summaries),
        "tick_ms": sum(per_tick(s, "elapsed_s") for s in summaries) / n,
        "process_cpu_ms_per_tick": sum(per_tick(s, "process_cpu_s") for s in summaries) / n,
        "python_cpu_ms_per_tick": sum(per_tick(s, "python_cpu_s") for s in summaries) / n,
        "phases": {p: {f: sum(s["phases"][p][f] for s in summaries) / n for f in summaries[0]["phases"][p]}
                   for p in summaries[0]["phases"]},
    }


def format_table(m: dict, title: str = "") -> str:
    """A markdown table of one (merged) summary: wall and CPU ms per tick
    per phase, then the process's CPU split into Python and the rest."""
    lines = [title, ""] if title else []
    lines += ["| phase | wall ms/tick | CPU ms/tick |", "|---|---:|---:|"]
    for p, v in m["phases"].items():
        cpu = f"{v['cpu_ms_per_tick']:.3f}" if not p.startswith("wait") else "–"
        lines.append(f"| {p} | {v['wall_ms_per_tick']:.3f} | {cpu} |")
    lines.append(f"| **tick** | {m['tick_ms']:.3f} | {m['python_cpu_ms_per_tick']:.3f} |")
    lines.append("")
    rest = m["process_cpu_ms_per_tick"] - m["python_cpu_ms_per_tick"]
    lines.append(f"process CPU {m['process_cpu_ms_per_tick']:.3f} ms/tick: the phases above "
                 f"{m['python_cpu_ms_per_tick']:.3f}, zenoh and the kernel outside them {rest:.3f}")
    return "\n".join(lines)
