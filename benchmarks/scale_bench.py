"""Scale benchmark: ``diskf-mesh up --hosts`` with 25, 50, 100 (and 200)
agent processes, 25 agents per "host" (a zenoh router and a shard of agents
each, on loopback, or each host in its own network namespace with
``--netns``; the world is a router too), in lockstep or in real time
(``--rate``). Prints one markdown table; not a test.

    python benchmarks/scale_bench.py [--agents 25,50,100] [--per-host 25] [--ticks 50]
                                     [--scenario random-geometric] [--single] [--rate HZ] [--netns]

    # real time at scale: 100 agents on 4 namespace hosts at 5 Hz; 200 agents at 2 Hz
    python benchmarks/scale_bench.py --agents 100 --netns --rate 5 --ticks 100
    python benchmarks/scale_bench.py --agents 200 --per-host 50 --rate 2 --ticks 40

``--netns`` (root, ``ip netns``): a hub namespace with a bridge, the world
in a namespace of its own and each host's router and shard in another
(``ip netns exec`` as the hosts file's prefix), 10.214.<n>.0/24; they are
deleted at the end.

Columns:
    hosts        routers + shards (``--per-host`` agents each); ``--single``
                 adds the one-host run of ``up`` (no --hosts: peers, or one router) for comparison
    first tick   seconds from starting ``up`` to the world opening tick 1
    ticks/s      tick 1 to the last report
    CPU ms/agent-tick  agents' CPU (user + system) over the ticks, per agent
                 per tick
    world CPU %  the world's share of all CPU over the ticks (world, routers,
                 hosts, agents)
    routers %    the routers' share
    RSS MB/agent the resident memory of an agent process (median of peaks)
    PSS MB/agent its proportional share (pages shared with the other agents
                 forked from the same zygote counted once over all of them):
                 what each more agent costs the machine
    missing      agent-ticks not reported
    missed %     real time: agent-ticks whose report was not in by the
                 tick's end (it never came: missing, or came later:
                 deadline_misses.late_reports), over all agent-ticks;
                 message misses: neighbours' messages not fused in time,
                 over those due

CPU is read from /proc for every process of the run, five times a second:
over the ticks = the last sample before the last report minus the first
sample after tick 1 (the world's ``startup_s`` and ``ticks_s``). The machine is shared: compare figures of one invocation.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from sim.launcher import network_of  # noqa: E402
from sim.netns import Namespaces  # noqa: E402

ROLES = {"sim.world": "world", "agents.agent": "agent", "sim.router": "router", "sim.host": "host",
         "sim.launcher": "up"}
TICK_S = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


def hosts_file(path: Path, n: int, per_host: int, port0: int, spaces=None) -> Path:
    """The hosts file; ``spaces`` (``Namespaces``): the world in the first
    namespace, host h in namespace h + 1."""
    world = f"tls/{spaces.addrs[0]}:{port0}" if spaces else f"tls/127.0.0.1:{port0}"
    lines = ["[world]", f'listen = "{world}"']
    if spaces:
        lines.append(f'prefix = ["ip", "netns", "exec", "{spaces.names[0]}"]')
    for h, lo in enumerate(range(1, n + 1, per_host)):
        hi = min(lo + per_host - 1, n)
        router = f"tls/{spaces.addrs[h + 1]}:{port0}" if spaces else f"tls/127.0.0.1:{port0 + 1 + h}"
        lines += [f"[hosts.h{h}]", f'agents = "{lo}-{hi}"', f'router = "{router}"']
        if spaces:
            lines.append(f'prefix = ["ip", "netns", "exec", "{spaces.names[h + 1]}"]')
    path.write_text("\n".join(lines) + "\n")
    return path


def pss(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def sample(run_id: str) -> dict:
    """pid -> (role, CPU seconds, RSS bytes) of the run's processes now."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            argv = (d / "cmdline").read_bytes().split(b"\0")
            if run_id.encode() not in argv:
                continue
            role = next((r for m, r in ROLES.items() if m.encode() in argv), None)
            stat = (d / "stat").read_text().rsplit(")", 1)[1].split()
            rss = int((d / "statm").read_text().split()[1]) * PAGE
        except (OSError, IndexError, ValueError):
            continue
        if role:
            out[int(d.name)] = (role, (int(stat[11]) + int(stat[12])) / TICK_S, rss)
    return out


def one(n: int, per_host: int | None, ticks: int, scenario: str, tmp: Path, port0: int, rate=None,
        netns: bool = False) -> dict:
    run_id = f"scale{n}{'h' if per_host else 's'}{os.getpid() % 1000}"
    est = tmp / f"{run_id}.json"
    cmd = [sys.executable, "-m", "sim.launcher", "--scenario", scenario, "--algorithm", "diskf", "--agents", str(n), "--ticks", str(ticks),
           "--run-id", run_id, "--estimates", str(est), "--json", str(tmp / f"{run_id}-res.json"),
           "--logs", str(tmp / run_id), "--quiet", "--startup-timeout", str(60 + 2 * n)]
    if rate:
        cmd += ["--rate", str(rate)]
    spaces = Namespaces(1 + -(-n // per_host), prefix="dks", octet=214) if netns and per_host else None
    if spaces:
        try:
            spaces.__enter__()
        except OSError as e:
            raise SystemExit(f"cannot build the namespaces (root and ip netns needed): {e}")
    try:
        if per_host:
            cmd += ["--hosts", str(hosts_file(tmp / f"{run_id}.toml", n, per_host, port0, spaces))]
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        samples = []  # (t, {pid: (role, cpu, rss)})
        shares, shares_at = {}, -10.0  # agent pid -> PSS, read every 5 s (a costly read)
        while proc.poll() is None:
            now = time.monotonic() - t0
            samples.append((now, sample(run_id)))
            if now - shares_at >= 5.0:
                shares_at = now
                for pid, (role, _, _) in samples[-1][1].items():
                    if role == "agent" and (v := pss(pid)) is not None:
                        shares[pid] = max(shares.get(pid, 0), v)
            time.sleep(0.2)
        out, err = proc.communicate()
    finally:
        if spaces:
            spaces.__exit__()
    if not est.exists():
        raise SystemExit(f"run of {n} agents failed (exit {proc.returncode}): {err.strip()[-500:]}")
    doc = json.loads(est.read_text())
    t_world = next((t for t, s in samples if any(r == "world" for r, _, _ in s.values())), 0.0)  # its start
    start, end = t_world + doc["startup_s"], t_world + doc["startup_s"] + doc["ticks_s"]
    first = next((s for t, s in samples if t >= start), samples[-1][1])
    last = next((s for t, s in reversed(samples) if t <= end and s), samples[-1][1])
    cpu = {}
    for pid, (role, c, _) in last.items():
        cpu[role] = cpu.get(role, 0.0) + c - first.get(pid, (role, 0.0, 0))[1]
    total = sum(cpu.values()) or 1e-9
    print(f"    CPU s over the ticks by role: {', '.join(f'{r} {c:.2f}' for r, c in sorted(cpu.items()))}; "
          f"{len(samples)} samples", file=sys.stderr)
    peak = {}
    for _, s in samples:
        for pid, (role, _, r) in s.items():
            if role == "agent":
                peak[pid] = max(peak.get(pid, 0), r)
    rss = list(peak.values())
    dm = doc.get("deadline_misses", {})
    # agent-ticks whose report was not in by the tick's end: never came, or came late
    missed = (doc.get("missing_agent_ticks", 0) + dm.get("late_reports", 0)) / (n * ticks)
    first_up = next((float(x) for x in [out.split("s after up started")[0].rsplit("(", 1)[-1]]
                     if "s after up started" in out), float("nan"))
    return {"agents": n, "hosts": (n + per_host - 1) // per_host if per_host else 1,
            "mode": ("netns " if spaces else "") + ("routers" if per_host else f"up ({network_of('auto', n)})"),
            "target": f"{rate:g} Hz" if rate else "lockstep", "first": doc["startup_s"], "first_up": first_up,
            "missed": missed, "message_misses": dm.get("message_miss_rate", float("nan")),
            "pss_mb": statistics.median(shares.values()) / 2**20 if shares else float("nan"),
            "rate": ticks / max(doc["ticks_s"], 1e-9),
            "cpu_agent_tick_ms": 1000 * cpu.get("agent", 0.0) / (n * ticks),
            "world_share": cpu.get("world", 0.0) / total, "router_share": cpu.get("router", 0.0) / total,
            "rss_mb": statistics.median(rss) / 2**20 if rss else float("nan"),
            "missing": doc.get("missing_agent_ticks", 0), "status": proc.returncode}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agents", default="25,50,100", help="agent counts (default %(default)s)")
    ap.add_argument("--per-host", type=int, default=25, help="agents per host (default %(default)s)")
    ap.add_argument("--ticks", type=int, default=50)
    ap.add_argument("--scenario", default="random-geometric")
    ap.add_argument("--single", action="store_true",
                    help="also the one-host run of each count (up without --hosts: peers, or one router above "
                         "sim.launcher.PEERS_UP_TO agents)")
    ap.add_argument("--rate", type=float, help="real time at this rate (up --rate); default: lockstep")
    ap.add_argument("--netns", action="store_true", help="every host (and the world) in a network namespace")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="diskf-scale-") as tmp:
        for n in (int(a) for a in args.agents.split(",")):
            for per_host in ((args.per_host, None) if args.single else (args.per_host,)):
                print(f"... {n} agents, {'routers' if per_host else 'peers'}", file=sys.stderr, flush=True)
                rows.append(one(n, per_host, args.ticks, args.scenario, Path(tmp), 17800 + 20 * len(rows),
                                args.rate, args.netns))
    print(f"{f'real time at {args.rate:g} Hz' if args.rate else 'lockstep'}, {args.scenario}, {args.ticks} ticks, "
          f"{os.cpu_count()} CPUs\n")
    print("| agents | hosts | shape | rate | first tick s (world / up) | ticks/s | missed % | message misses % "
          "| CPU ms/agent-tick | world CPU % | routers % | RSS MB/agent | PSS MB/agent | missing | exit |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['agents']} | {r['hosts']} | {r['mode']} | {r['target']} | {r['first']:.1f} / {r['first_up']:.1f} "
              f"| {r['rate']:.1f} | {100 * r['missed']:.2f} | {100 * r['message_misses']:.2f} | "
              f"{r['cpu_agent_tick_ms']:.2f} | {100 * r['world_share']:.0f} | {100 * r['router_share']:.0f} | "
              f"{r['rss_mb']:.0f} | {r['pss_mb']:.0f} | {r['missing']} | {r['status']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
