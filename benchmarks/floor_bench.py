"""The protocol's floor: the lockstep of a mesh run with no estimation work.

    python benchmarks/floor_bench.py [--agents 9,25,50] [--ticks 300] [--repeat 3] [--no-project] [--insecure]

A bare world and N bare agents, each its own OS process and zenoh-python
session, configured as ``diskf-mesh up`` configures them: the same zenoh
options and shape (``sim.launcher.loopback_options``: the world listens on
127.0.0.1, every agent connects to it and listens on port 0, no multicast
scouting; above ``sim.launcher.PEERS_UP_TO`` agents
``routed_loopback_options``: one router, ``diskf-mesh router``, every agent
its client), over TLS with mutual authentication and the run's access control
from fresh credentials of the run (``diskf_mesh.mesh.security.credentials``, one
identity per process, as ``up`` makes them), the world's batching time
limit (``sim.world.HOLD_MS``), zenoh's rx runtime of one thread, the callbacks'
thread states kept (``transport.direct_callback``), and the
project's key layout (``diskf_mesh.mesh.wire.keys``), so the access control
checks the same keys. With ``--insecure`` both the floor and the project
run plain zenoh (``up --insecure``). They exchange per tick exactly the
messages of the project's protocol, with the project's sizes and addressing:

* world -> agent i: its measurement (not express, ~60 bytes), then the tick
  (express; the positions of all N agents and the live set);
* agent i -> the agents in range at tick k: ONE message of the size of a
  DISKF message (n = 2, m = 1), on the addressed key ``agent/i/msg/_j_l_``
  that every agent subscribes to with ``agent/*/msg/$*_<i>_$*``;
* liveliness: an alive token per process, then a ready token per agent once
  it sees the world and every agent (the project's start-up barrier);
* agent i -> world: its report (the size of a project report) once every
  neighbour's message of tick k is in.

The links per tick come from the project's own scenario (the same
``--scenario``/``--agents``), so both runs route the same messages. The
bytes are zeros: nothing is decoded, checked or computed. What is left is
what the protocol costs in zenoh, Python callbacks and the kernel: the rate
the project could at best reach with the same shape of run on this machine.

Then, unless ``--no-project``, the project's own ``up`` of the same scenario
and agents runs right after each floor run (``mesh_bench.run_one``), and the
table prints both rates and the project's share of the floor. The machine is
shared and noisy: compare the ratio of one invocation, not rates across
invocations.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

def cpu_seconds() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def sizes() -> dict:
    """Bytes of the project's payloads for n = 2, m = 1, p = 1."""
    import numpy as np

    from diskf_mesh.mesh.wire import codec as wire
    from mesh_bench import message_bytes

    report = wire.encode_report("a1b2c3d4", 50, 200, np.zeros(2), np.eye(2), np.zeros(1), True,
                                {"sent": 200, "fused": 400, "published": 200})
    meas = wire.encode_measurement("a1b2c3d4", 200, 50, True, np.zeros(1))
    return {"msg": message_bytes(), "report": len(report), "meas": len(meas)}


def links_of(scenario: str, agents: int | None, ticks: int):
    """(K, N, N) bool links and the agent ids of the project's scenario."""
    from diskf_mesh.data.scenario import load_scenario, simulate

    scn = load_scenario(scenario, agents=agents).with_overrides(steps=ticks)
    tr = simulate(scn, [0])
    return tr.links[0], [a.id for a in scn.agents]


def zenoh_session(role: str, identity: str, args):
    """A session of the floor's ``role`` ("world" or "agent") with the
    options ``up`` gives that process (see the module docstring)."""
    import zenoh

    from diskf_mesh.mesh.process.transport import BATCHING, ZENOH_RUNTIME
    from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
    from sim.world import HOLD_MS

    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
    zenoh.init_log_from_env_or("error")
    base = ZenohOptions(credentials=args.credentials) if args.credentials else ZenohOptions(insecure=True)
    world, _, agent = network_options(args.port, args.router_port, base)
    opts = (world if role == "world" else agent).as_identity(identity, args.run_id)
    conf = opts.to_config()
    if role == "world":
        conf.insert_json5(f"{BATCHING}/time_limit", str(HOLD_MS))
    return zenoh, zenoh.open(conf)


def network_options(port: int, router_port: int, base) -> tuple:
    """(world, router or None, agent) options of ``up``'s shape on one host:
    a peer mesh (``router_port`` 0) or every agent a client of one router
    (``sim.launcher.routed_loopback_options``)."""
    from sim.launcher import loopback_options, routed_loopback_options

    if router_port:
        return routed_loopback_options(port, router_port, base)
    world, agent = loopback_options(port, base)
    return world, None, agent


def publisher(zenoh, session, cache: dict, key: str, express: bool = True):
    pub = cache.get(key)
    if pub is None:
        pub = cache[key] = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                     express=express, allowed_destination=zenoh.Locality.REMOTE)
    return pub


# --------------------------------------------------------------------------
# the bare agent
# --------------------------------------------------------------------------
def agent_main(args) -> int:
    from diskf_mesh.mesh.process.transport import direct_callback
    from diskf_mesh.mesh.security import credentials
    from diskf_mesh.mesh.wire.keys import Keys, new_nonce

    links, ids = links_of(args.scenario, args.n_agents, args.ticks)
    me = args.id
    j = ids.index(me)
    nbrs = [[ids[s] for s in range(len(ids)) if s != j and links[k, j, s]] for k in range(links.shape[0])]
    sz = sizes()
    msg, report = bytes(sz["msg"]), bytes(sz["report"])
    zenoh, s = zenoh_session("agent", credentials.agent_identity(me), args)
    keys, nonce = Keys(args.run_id), new_nonce()
    pubs = {}
    lock = threading.Lock()
    state = {"k": 1, "tick": set(), "meas": set(), "got": {}, "open": False, "stop": threading.Event()}
    seen = set()
    ready_declared = []

    def advance():
        while True:
            k = state["k"]
            if not state["open"]:
                if k not in state["tick"] or k not in state["meas"]:
                    return
                to = nbrs[k - 1]
                if to:
                    publisher(zenoh, s, pubs, keys.msg(me, to=to)).put(msg, attachment=str(k).encode())
                state["open"] = True
            if state["got"].get(k, 0) < len(nbrs[k - 1]):
                return
            publisher(zenoh, s, pubs, keys.report(me)).put(report)
            state["got"].pop(k, None)
            state["tick"].discard(k)
            state["open"] = False
            state["k"] = k + 1

    def on_tick(sample):
        k = int(sample.attachment.to_bytes()) if sample.attachment is not None else 0
        with lock:
            if k < 0:
                state["stop"].set()
                return
            state["tick"].add(k)
            advance()

    def on_meas(sample):
        k = int(sample.attachment.to_bytes())
        with lock:
            state["meas"].add(k)
            advance()

    def on_msg(sample):
        k = int(sample.attachment.to_bytes())
        with lock:
            state["got"][k] = state["got"].get(k, 0) + 1
            advance()

    def on_alive(sample):
        with lock:
            kind, who = keys.parse(str(sample.key_expr))
            seen.add("world" if kind == "alive-world" else str(who))
            if not ready_declared and {str(i) for i in ids} | {"world"} <= seen:
                ready_declared.append(s.liveliness().declare_token(keys.ready(me, nonce)))

    kept = set()
    direct = lambda fn: direct_callback(zenoh, fn, kept)  # noqa: E731
    subs = [s.declare_subscriber(keys.tick, direct(on_tick)),
            s.declare_subscriber(keys.meas(me), direct(on_meas)),
            s.declare_subscriber(keys.msg_to(me), direct(on_msg)),
            s.liveliness().declare_subscriber(f"{keys.root}/alive/**", direct(on_alive), history=True)]
    token = s.liveliness().declare_token(keys.alive(me, nonce))
    state["stop"].wait(args.timeout)
    for sub in subs:  # no callback after this (one would still use the state above)
        sub.undeclare()
    with lock:
        for t in (token, *ready_declared):
            t.undeclare()
    s.close()
    return 0


# --------------------------------------------------------------------------
# the bare world
# --------------------------------------------------------------------------
def world_main(args) -> int:
    from diskf_mesh.mesh.process.transport import direct_callback
    from diskf_mesh.mesh.security import credentials
    from diskf_mesh.mesh.wire.keys import Keys, new_nonce

    links, ids = links_of(args.scenario, args.n_agents, args.ticks)
    N, K = len(ids), args.ticks
    sz = sizes()
    meas, tick = bytes(sz["meas"]), bytes(150 + 16 * N + 8 * N)  # the project's tick: header, positions, live
    zenoh, s = zenoh_session("world", credentials.WORLD, args)
    keys = Keys(args.run_id)
    pubs = {}
    cv = threading.Condition()
    ready, reports = set(), {}
    done = threading.Event()
    t = {}

    def open_tick(k):
        att = str(k).encode()
        for i in ids:
            publisher(zenoh, s, pubs, keys.meas(i), express=False).put(meas, attachment=att)
        publisher(zenoh, s, pubs, keys.tick).put(tick, attachment=att)

    state = {"k": 0}

    def on_report(sample):
        with cv:
            k = state["k"]
            reports[k] = reports.get(k, 0) + 1
            if reports[k] == N:
                if k == K:
                    t["end"] = time.monotonic()
                    done.set()
                    return
                state["k"] = k + 1
                open_tick(k + 1)

    def on_ready(sample):
        with cv:
            ready.add(keys.parse(str(sample.key_expr))[1])
            cv.notify_all()

    kept = set()
    direct = lambda fn: direct_callback(zenoh, fn, kept)  # noqa: E731
    subs = [s.declare_subscriber(f"{keys.root}/agent/*/report", direct(on_report)),
            s.liveliness().declare_subscriber(keys.ready("*"), direct(on_ready), history=True)]
    token = s.liveliness().declare_token(keys.world(new_nonce()))
    with cv:
        if not cv.wait_for(lambda: len(ready) >= N, args.timeout):
            print(json.dumps({"error": f"only {len(ready)} of {N} agents ready"}), flush=True)
            return 1
        t["first"] = time.monotonic()
        state["k"] = 1
        open_tick(1)
    ok = done.wait(args.timeout)
    publisher(zenoh, s, pubs, keys.tick).put(b"", attachment=b"-1")
    time.sleep(0.2)
    print(json.dumps({"ticks_s": t["end"] - t["first"] if ok else None, "ticks": K, "agents": N}), flush=True)
    for sub in subs:
        sub.undeclare()
    token.undeclare()
    s.close()
    return 0 if ok else 1


# --------------------------------------------------------------------------
# the benchmark
# --------------------------------------------------------------------------
def floor_run(scenario: str, agents: int | None, ticks: int, timeout: float, workdir: Path,
              insecure: bool = False) -> dict:
    """One floor run; its own fresh credentials in ``workdir`` unless ``insecure``."""
    from diskf_mesh.mesh.security import credentials
    from diskf_mesh.mesh.process import runspec
    from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
    from sim.launcher import free_ports, network_of

    _, ids = links_of(scenario, agents, ticks)
    port, router_port = free_ports(2) if network_of("auto", len(ids)) == "router" else (*free_ports(1), 0)
    run_id = f"b{time.monotonic_ns()}"
    common = ["--scenario", scenario, "--ticks", str(ticks), "--port", str(port), "--router-port", str(router_port),
              "--run-id", run_id, "--timeout", str(timeout)] + (["--n-agents", str(agents)] if agents else [])
    base = ZenohOptions(insecure=True)
    if not insecure:
        creds = str(credentials.make(workdir / f"credentials-{run_id}", run_id, ids))
        common += ["--credentials", creds]
        base = ZenohOptions(credentials=creds)
    me = [sys.executable, str(Path(__file__).resolve())]
    cpu0, t0 = cpu_seconds(), time.monotonic()
    world = subprocess.Popen(me + ["world", *common], stdout=subprocess.PIPE, text=True)
    router = network_options(port, router_port, base)[1]
    procs = ([subprocess.Popen(runspec.router_command(run_id, router), stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)] if router else [])
    procs += [subprocess.Popen(me + ["agent", "--id", str(i), *common]) for i in ids]
    try:
        out, _ = world.communicate(timeout=timeout + 30)
    finally:
        if router:  # a router runs until told to stop
            procs[0].terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    wall, cpu = time.monotonic() - t0, cpu_seconds() - cpu0
    doc = json.loads(out.strip().splitlines()[-1]) if out.strip() else {"error": "no output"}
    if doc.get("ticks_s") is None:
        return {"agents": len(ids), "error": doc.get("error", "did not finish")}
    return {"agents": len(ids), "ticks_per_s": ticks / doc["ticks_s"], "cpu_ms_per_tick": 1e3 * cpu / ticks,
            "wall_s": wall}


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] in ("world", "agent"):
        p = argparse.ArgumentParser()
        p.add_argument("role")
        p.add_argument("--id", type=int)
        p.add_argument("--scenario")
        p.add_argument("--n-agents", type=int)
        p.add_argument("--ticks", type=int)
        p.add_argument("--port", type=int)
        p.add_argument("--router-port", type=int, default=0)
        p.add_argument("--run-id")
        p.add_argument("--timeout", type=float)
        p.add_argument("--credentials")
        a = p.parse_args(argv)
        return world_main(a) if a.role == "world" else agent_main(a)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--agents", default="9,25,50",
                   help="comma list of agent counts; 9 runs Scenario 2 (dynamic), others random-geometric")
    p.add_argument("--ticks", type=int, default=300)
    p.add_argument("--repeat", type=int, default=3, help="pairs of runs per agent count (median kept)")
    p.add_argument("--algorithm", default="diskf")
    p.add_argument("--no-project", action="store_true", help="the floor alone")
    p.add_argument("--insecure", action="store_true",
                   help="plain zenoh for both (up --insecure); default: both over TLS with the run's access control")
    p.add_argument("--timeout", type=float, default=600.0)
    p.add_argument("--json", help="also write the rows as JSON")
    args = p.parse_args(argv)
    from mesh_bench import run_one

    settings = [("dynamic", None) if int(n) == 9 else ("random-geometric", int(n)) for n in args.agents.split(",")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="floor-bench-") as tmp:
        for scenario, n in settings:
            floors, projects = [], []
            for _ in range(max(args.repeat, 1)):
                f = floor_run(scenario, n, args.ticks, args.timeout, Path(tmp), args.insecure)
                floors.append(f)
                print("floor " + json.dumps(f), file=sys.stderr, flush=True)
                if not args.no_project:
                    r = run_one(scenario, n, args.ticks, args.algorithm, Path(tmp), insecure=args.insecure)
                    projects.append(r)
                    print("project " + json.dumps(r), file=sys.stderr, flush=True)
            rows.append((scenario, n, floors, projects))
    print(f"\nThe protocol's floor beside the project ({args.algorithm}), {args.ticks} ticks, one process per agent, "
          f"zenoh on loopback, {'plain tcp (--insecure)' if args.insecure else 'TLS + access control'} for both, "
          f"median of {args.repeat} interleaved pairs\n")
    print("| scenario | agents | floor ticks/s | project ticks/s | project / floor: median of pairs (range) "
          "| floor CPU ms/tick | project CPU ms/tick | project first tick (s) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    out = []
    for scenario, n, floors, projects in rows:
        fr = [f["ticks_per_s"] for f in floors if "error" not in f]
        pr = [r["ticks_per_s"] for r in projects if "error" not in r]
        pairs = sorted(r["ticks_per_s"] / f["ticks_per_s"] for f, r in zip(floors, projects)
                       if "error" not in f and "error" not in r)
        agents = (floors[0] if floors else {}).get("agents", n)
        fcpu = statistics.median([f["cpu_ms_per_tick"] for f in floors if "error" not in f] or [float("nan")])
        pcpu = statistics.median([r["cpu_ms_per_tick"] for r in projects if "error" not in r] or [float("nan")])
        first = statistics.median([r["first_tick_s"] for r in projects if "error" not in r] or [float("nan")])
        ratio = f"{statistics.median(pairs):.2f} ({pairs[0]:.2f}–{pairs[-1]:.2f})" if pairs else "–"
        print(f"| {scenario} | {agents} | {statistics.median(fr) if fr else float('nan'):.0f} "
              f"| {statistics.median(pr) if pr else float('nan'):.0f} | {ratio} | {fcpu:.1f} | {pcpu:.1f} "
              f"| {first:.2f} |")
        out.append({"scenario": scenario, "agents": agents, "floor": floors, "project": projects})
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
