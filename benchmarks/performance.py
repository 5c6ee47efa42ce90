"""docs/performance.md from one command: the hardware it ran on, then each
benchmark's own Markdown output under a heading naming its command.

    python benchmarks/performance.py [--out docs/performance.md] [--only engine,record,...] [--quick]

Every section is a ratio measured side by side in one invocation of its
benchmark (engine against the plain oracle, ``up`` with and without
``--record`` or ``--live``, the protocol's floor against the project, TLS
against plain TCP), so the figures compare even on a machine that other work
keeps busy; absolute rates are that machine's. Takes 20-40 minutes on two
cores (``--quick``: a few). Run it on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import importlib.metadata as md
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# (key, title, what the ratio is, script and its arguments, --quick arguments)
SECTIONS = [
    ("engine", "Engine: the batched engine against a plain per-agent loop",
     "agent-steps (one agent, one tick) per CPU second; the engine and the plain DISKF oracle are timed in the "
     "same interleaved rounds, best of the rounds",
     ["benchmarks/engine_bench.py"], ["benchmarks/engine_bench.py", "--quick"]),
    ("mesh", "The mesh: `diskf-mesh up` in lockstep",
     "ticks/s from tick 1 to the last report, and the CPU of every process per tick",
     ["benchmarks/mesh_bench.py", "--agents", "4,9,25,50", "--ticks", "200", "--repeat", "3"],
     ["benchmarks/mesh_bench.py", "--agents", "9", "--ticks", "100"]),
    ("floor", "The protocol's floor against the project",
     "a bare world and bare agents on `up`'s transport and shape (TLS, access control, the same keys, sizes and "
     "links) with no decoding, checks or math, then the project's `up` of the same scenario: the ratio is per pair",
     ["benchmarks/floor_bench.py", "--agents", "9,25,50", "--ticks", "300", "--repeat", "2"],
     ["benchmarks/floor_bench.py", "--agents", "9", "--ticks", "100", "--repeat", "1"]),
    ("record", "What recording costs",
     "`up` with and without `--record`, back to back (which goes first alternates); ratios per pair",
     ["benchmarks/record_bench.py", "--ticks", "300", "--repeat", "8"],
     ["benchmarks/record_bench.py", "--ticks", "100", "--repeat", "2"]),
    ("live", "What `up --live` costs with nobody watching",
     "`up` and `up --live` with no browser, in turns; the world's rate from tick 1 to the last report",
     ["benchmarks/live_cost.py", "--ticks", "300", "--repeat", "5"],
     ["benchmarks/live_cost.py", "--ticks", "100", "--repeat", "2"]),
    ("tls", "What TLS and access control cost one message",
     "two zenoh sessions in one process, ping-pong over loopback: plain TCP, TLS, TLS with access control, "
     "in interleaved rounds",
     ["benchmarks/tls_bench.py", "--messages", "2000", "--rounds", "5"],
     ["benchmarks/tls_bench.py", "--messages", "300", "--rounds", "2"]),
    ("startup", "Start-up: seconds from `up` to tick 1",
     "the zygote forking every process against a fresh interpreter per process, interleaved",
     ["benchmarks/startup_bench.py", "--agents", "9,50", "--repeat", "3"],
     ["benchmarks/startup_bench.py", "--agents", "9", "--repeat", "1"]),
    ("realtime", "Real time: deadline misses and error against the tick rate",
     "`up --rate HZ` for every estimator; each cell is misses % / MAE(state), beside the lockstep's MAE",
     ["benchmarks/realtime_bench.py", "--ticks", "50", "--algorithms", "all", "--sizes", "dynamic,25"],
     ["benchmarks/realtime_bench.py", "--ticks", "30", "--algorithms", "diskf", "--sizes", "dynamic",
      "--rates", "10,50"]),
    ("scale", "Several hosts: routers and shards on loopback",
     "`up --hosts` with 25 agents per host (a zenoh router and a shard each), lockstep",
     ["benchmarks/scale_bench.py", "--agents", "25,50,100", "--ticks", "50"],
     ["benchmarks/scale_bench.py", "--agents", "25", "--ticks", "20"]),
]


def _version(dist: str) -> str:
    try:
        return md.version(dist)
    except md.PackageNotFoundError:
        return "not installed"


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else the platform's word)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def hardware() -> str:
    """One Markdown paragraph naming the machine and the software measured."""
    return (f"Measured on: {cpu_model()}, {os.cpu_count()} cores, {platform.system()} {platform.release()}; "
            f"Python {platform.python_version()}, numpy {_version('numpy')}, eclipse-zenoh "
            f"{_version('eclipse-zenoh')}, diskf-mesh {_version('diskf-mesh')}; "
            f"{time.strftime('%Y-%m-%d', time.gmtime())}.")


def run_section(args: list[str]) -> str:
    """The benchmark's standard output (its Markdown), or its error; then
    the wall-clock and CPU seconds of it and its children."""
    with tempfile.TemporaryDirectory(prefix="diskf-perf-") as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        done = subprocess.run([sys.executable, *(a.replace("{tmp}", tmp) for a in args)], cwd=ROOT,
                              capture_output=True, text=True)
        wall = time.monotonic() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        out = done.stdout.replace(tmp, "DIR").strip()
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        return f"The benchmark failed (exit {done.returncode}): `{tail}`\n"
    return (out + "\n\n" if out else "") + \
        f"This section took {wall:.0f} s of wall-clock time and {cpu:.0f} s of CPU.\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "performance.md"))
    ap.add_argument("--only", help="comma list of sections: " + ",".join(s[0] for s in SECTIONS))
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke run of the generator")
    a = ap.parse_args(argv)
    keys = [s[0] for s in SECTIONS]
    only = a.only.split(",") if a.only else keys
    unknown = sorted(set(only) - set(keys))
    if unknown:
        ap.error(f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(keys)}")
    parts = ["# Performance\n",
             "Generated by `python benchmarks/performance.py` (each section names its own command; run one alone "
             "with `--only KEY`). Every table sets two things side by side in one invocation, so its ratios "
             "compare; absolute rates are those of the machine below.\n",
             hardware() + "\n"]
    for key, title, what, full, quick in SECTIONS:
        if key not in only:
            continue
        args = quick if a.quick else full
        shown = " ".join(a.replace("{tmp}", "DIR") for a in args)
        print(f"{key}: python {shown}", file=sys.stderr, flush=True)
        parts.append(f"## {title}\n\n`python {shown}`: {what}.\n\n{run_section(args)}")
    text = "\n".join(parts)
    tmp = Path(a.out + ".tmp")
    tmp.write_text(text)
    tmp.replace(a.out)
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
