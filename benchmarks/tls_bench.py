"""What TLS and zenoh's access control cost one message: two zenoh sessions in
one process, ping-pong over loopback, as plain TCP (``--insecure``), TLS with
mutual authentication, and TLS with the run's access control (what every
mesh process runs, ``diskf_mesh.mesh.security.credentials``). Not a test.

    python benchmarks/tls_bench.py [--messages 2000] [--rounds 5] [--size 163]

Rounds interleave the three set-ups, so that a busy machine slows them
alike; it prints the median round trip and the CPU of the process per round
trip (both sessions, each message sent and received once per direction),
best and median over the rounds.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout's sim, as the other benchmarks do
from diskf_mesh.mesh.security import credentials  # noqa: E402
from diskf_mesh.mesh.wire.keys import Keys  # noqa: E402
from diskf_mesh.mesh.process.transport import ZenohTransport  # noqa: E402
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions  # noqa: E402
from sim.launcher import free_port  # noqa: E402

RUN = "tls-bench"


def options(kind: str, creds: Path, port: int) -> tuple:
    proto = "tcp" if kind == "tcp" else "tls"
    base = ZenohOptions(no_multicast_scouting=True, run_id=RUN,
                        cfg=("access_control/enabled:false",) if kind == "tls" else (),
                        **({} if kind == "tcp" else {"credentials": str(creds)}))
    return (replace(base, listen=(f"{proto}/127.0.0.1:{port}",), identity=credentials.WORLD),
            replace(base, connect=(f"{proto}/127.0.0.1:{port}",), identity=credentials.agent_identity(1)))


def round_trips(kind: str, creds: Path, messages: int, size: int) -> tuple:
    """(median round trip in us, process CPU us per round trip)."""
    keys = Keys(RUN)
    world_opts, agent_opts = options(kind, creds, free_port())
    with ZenohTransport(world_opts) as w, ZenohTransport(agent_opts) as a:
        got = threading.Event()
        a.subscribe(keys.tick, lambda k, p: a.put(keys.report(1), p))   # the agent answers the world
        w.subscribe(keys.report("*"), lambda k, p: got.set())
        payload = bytes(size)
        deadline = time.monotonic() + 10
        while not got.is_set():  # connected both ways
            w.put(keys.tick, payload)
            got.wait(0.05)
            if time.monotonic() > deadline:
                raise RuntimeError(f"{kind}: the sessions did not connect")
        rtts = []
        cpu0 = time.process_time()
        for _ in range(messages):
            got.clear()
            t0 = time.perf_counter()
            w.put(keys.tick, payload)
            got.wait(5)
            rtts.append(time.perf_counter() - t0)
        cpu = time.process_time() - cpu0
    return 1e6 * statistics.median(rtts), 1e6 * cpu / messages


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--messages", type=int, default=2000)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--size", type=int, default=163, help="payload bytes (an agent's message is 163)")
    args = p.parse_args(argv)
    kinds = ("tcp", "tls", "tls+acl")
    out = {k: [] for k in kinds}
    with tempfile.TemporaryDirectory() as tmp:
        creds = credentials.make(Path(tmp) / "creds", RUN, [1])
        for _ in range(args.rounds):
            for k in kinds:
                out[k].append(round_trips(k, creds, args.messages, args.size))
    print(f"\n{args.messages} round trips of {args.size} bytes per round, {args.rounds} rounds, loopback\n")
    print("| link | round trip us: median round (best) | CPU us per round trip: median round (best) |")
    print("|---|---:|---:|")
    for k in kinds:
        rtt, cpu = zip(*out[k])
        print(f"| {k} | {statistics.median(rtt):.0f} ({min(rtt):.0f}) "
              f"| {statistics.median(cpu):.0f} ({min(cpu):.0f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
