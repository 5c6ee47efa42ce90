"""Start-up of ``diskf-mesh up``: seconds from the command to tick 1.

    python benchmarks/startup_bench.py [--agents 9,50,100] [--repeat 1] [--before /work/main]

For each agent count (9: Scenario 2, ``dynamic``; others
``random-geometric``) it runs ``up --ticks 3`` with each way of starting the
processes, interleaved, in one invocation (the machine is shared: compare
the figures of one invocation):

    fork    this checkout: the zygote (``sim.zygote``) forks every process
    exec    this checkout, ``DISKF_MESH_SPAWN=exec``: a fresh interpreter each
    before  ``--before TREE``: another checkout (e.g. an earlier
            commit), run with that tree's ``.venv/bin/python``

Columns: first tick after the command started (this checkout prints it:
"s after up started"; for ``before``, the world process's start time
(/proc, 10 ms) minus the command's start, plus the launcher's "first tick
after X s", which counts from when it started the world), the CPU seconds
of the whole run (every process, ``RUSAGE_CHILDREN``), and the exit status.
"""
from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLK = os.sysconf("SC_CLK_TCK")


def cpu_seconds() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def world_start(run_id: str, proc) -> float | None:
    """CLOCK_BOOTTIME seconds at which the run's world process started."""
    while proc.poll() is None:
        for d in Path("/proc").iterdir():
            if not d.name.isdigit():
                continue
            try:
                argv = (d / "cmdline").read_bytes().split(b"\0")
                if b"sim.world" in argv and run_id.encode() in argv:
                    return int((d / "stat").read_text().rsplit(")", 1)[1].split()[19]) / CLK
            except (OSError, ValueError, IndexError):
                continue
        time.sleep(0.01)
    return None


def one(mode: str, n: int, tmp: Path, before: Path | None) -> dict:
    scenario = ["--scenario", "dynamic"] if n == 9 else ["--scenario", "random-geometric", "--agents", str(n)]
    run_id = f"su{mode}{n}{time.monotonic_ns() % 100000}"
    python = str(before / ".venv" / "bin" / "python") if mode == "before" else sys.executable
    env = {**os.environ, **({"DISKF_MESH_SPAWN": "exec"} if mode == "exec" else {})}
    cmd = [python, "-m", "sim.launcher", *scenario, "--algorithm", "diskf", "--ticks", "3", "--run-id", run_id, "--quiet",
           "--json", str(tmp / f"{run_id}.json"), "--logs", str(tmp / run_id), "--startup-timeout", "120"]
    cpu0 = cpu_seconds()
    t0 = time.clock_gettime(time.CLOCK_BOOTTIME)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            cwd=before if mode == "before" else None)
    started = world_start(run_id, proc)
    out, err = proc.communicate(timeout=600)
    cpu = cpu_seconds() - cpu0
    after_start = re.search(r"first tick after ([0-9.]+) s", out)
    after_up = re.search(r"\(([0-9.]+) s after up started\)", out)
    if after_up:
        first = float(after_up.group(1))
    elif after_start and started is not None:
        first = started - t0 + float(after_start.group(1))
    else:
        first = float("nan")
    return {"mode": mode, "agents": n, "first_s": first, "cpu_s": cpu, "status": proc.returncode,
            "error": "" if proc.returncode == 0 else (err.strip().splitlines() or ["?"])[-1][:200]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agents", default="9,50,100")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--before", type=Path, help="another checkout to compare (its .venv/bin/python)")
    ap.add_argument("--modes", default="fork,exec", help="of fork, exec (default %(default)s)")
    args = ap.parse_args(argv)
    modes = args.modes.split(",") + (["before"] if args.before else [])
    rows = []
    with tempfile.TemporaryDirectory(prefix="startup-bench-") as tmp:
        for n in (int(a) for a in args.agents.split(",")):
            for _ in range(args.repeat):
                for mode in modes:
                    r = one(mode, n, Path(tmp), args.before)
                    print(f"... {r}", file=sys.stderr, flush=True)
                    rows.append(r)
    print(f"\n`up --ticks 3`, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the end; "
          f"median of {args.repeat}\n")
    print("| agents | " + " | ".join(f"{m}: first tick s / CPU s" for m in modes) + " |")
    print("|---:|" + "---:|" * len(modes))
    for n in dict.fromkeys(r["agents"] for r in rows):
        cells = []
        for m in modes:
            mine = [r for r in rows if r["agents"] == n and r["mode"] == m]
            ok = [r for r in mine if r["status"] == 0]
            cells.append(f"{statistics.median(r['first_s'] for r in ok):.2f} / "
                         f"{statistics.median(r['cpu_s'] for r in ok):.1f}" if ok else f"failed ({mine[0]['error']})")
        print(f"| {n} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
