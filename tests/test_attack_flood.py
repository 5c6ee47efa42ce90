"""Floods at a real mesh run: the receive path's limits hold.

``diskf-mesh up`` runs Scenario 2 (seed 7, ``--estimates``) as real processes
on loopback, in the mesh without access control (an intruder on the host can
join it; ``up_argv`` builds that command line, in one place). An injector,
a plain zenoh session on the world's port (read from the world's command
line, as an intruder would), floods every agent:

    before tick 1   1 MB messages on the agents' message keys, valid msgpack
                    naming tick 1 (they used to wait, held, for tick 1)
    mid-run         garbage under random sender ids; maps of 130,000 keys
                    (~0.9 MB) under random and real ids; world ticks
                    numbered far ahead and beyond the run

and listens to the world's ticks to time the run. Then: the estimates equal
the engine's bit for bit, every agent's RSS stayed within ``RSS_GROWTH_MB``
of its own before the flood, every log within ``LOG_BYTES``, the tick rate
after the flood is back within 20 % of the same run's before it, ``up``
exited 0 and the results have every agent-tick.
"""
from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.keys import Keys, address
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from mesh_helpers import assert_same, reference

pytestmark = [pytest.mark.mesh, pytest.mark.slow]

SEED = 7
TICKS = 1500
PRE = (100, 350)       # ticks over which the rate before the flood is measured
FLOOD_S = 6.0          # how long the mid-run flood lasts (or until tick TICKS - 600)
WINDOW = 150           # ticks per window of the rate after the flood
BIG_BEFORE = 150       # 1 MB messages sent before tick 1 (at most; they stop at tick 1)
RSS_GROWTH_MB = 64     # an agent's RSS may grow at most this much over its own before the flood
RSS_MAX_MB = 200       # and never exceed this, before tick 1 included
LOG_BYTES = 64 << 10   # every child's log stays below this
RUN_TIMEOUT_S = 300.0


def up_argv(tmp_path: Path, run_id: str) -> list:
    """The one command line of the run under attack: ``up --insecure``, the
    mesh an outsider can reach (the default run is credentialed: its receive
    path never sees these floods)."""
    return [sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--algorithm", "diskf", "--ticks", str(TICKS),
            "--seed", str(SEED), "--run-id", run_id, "--estimates", str(tmp_path / "estimates.json"), "--json", str(tmp_path / "results.json"),
            "--logs", str(tmp_path / "logs"), "--quiet", "--collect-timeout", "30", "--tick-timeout", "60", "--insecure"]


def processes_of(run_id: str) -> dict:
    """{pid: argv} of the world and agent processes of a run (from /proc, as
    ``ps`` shows them to anyone on the host)."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            argv = (d / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue
        if run_id in argv and ("sim.world" in argv or "agents.agent" in argv):
            out[int(d.name)] = argv
    return out


def listening(endpoint: str) -> bool:
    """Whether a TCP endpoint ``tcp/host:port`` accepts connections."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    try:
        socket.create_connection((host, int(port)), timeout=0.5).close()
        return True
    except OSError:
        return False


def rss_mb(pid: int) -> float:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0
    found = re.search(r"VmRSS:\s+(\d+) kB", text)  # none once the process is a zombie
    return int(found.group(1)) / 1024 if found else 0.0


class Injector:
    """A zenoh session of an intruder: floods, and times the world's ticks."""

    def __init__(self, endpoint: str, run_id: str):
        import zenoh
        self.block = zenoh.CongestionControl.BLOCK  # every payload delivered: the flood is paced by the mesh
        self.remote = zenoh.Locality.REMOTE         # its own forged ticks do not time the run
        self.session = zenoh.open(ZenohOptions(connect=(endpoint,), listen=("tcp/127.0.0.1:0",),
                                               no_multicast_scouting=True).to_config())
        self.keys = Keys(run_id)
        self.seen = {}          # tick -> monotonic time it was heard
        self.last_tick = None   # the latest tick as the world sent it (bytes)
        self.sent = 0
        self.session.declare_subscriber(self.keys.tick, self._on_tick)

    def _on_tick(self, sample) -> None:
        data = sample.payload.to_bytes()
        t = msgpack.unpackb(data).get("t")
        self.seen.setdefault(t, time.monotonic())
        self.last_tick = data

    def peers(self) -> int:
        return len(list(self.session.info.peers_zid()))

    @property
    def tick(self) -> int:
        return max(self.seen, default=0)

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=self.block, allowed_destination=self.remote)
        self.sent += 1

    def close(self) -> None:
        self.session.close()


def wait_until(cond, timeout: float, proc: subprocess.Popen, step: float = 0.02) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"up ended early with {proc.returncode}")
        if time.monotonic() > end:
            raise AssertionError("timed out")
        time.sleep(step)


def rate(seen: dict, first: int, last: int) -> float:
    return (last - first) / (seen[last] - seen[first])


class RssSampler(threading.Thread):
    """Samples the RSS of every agent process of a run, every ``period`` s."""

    def __init__(self, run_id: str, period: float = 0.2):
        super().__init__(daemon=True)
        self.run_id, self.period = run_id, period
        self.peak = {}     # pid -> MB
        self.last = {}     # pid -> MB
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.is_set():
            for p, argv in processes_of(self.run_id).items():
                if "agents.agent" in argv:
                    mb = rss_mb(p)
                    self.last[p] = mb
                    self.peak[p] = max(self.peak.get(p, 0.0), mb)
            self.done.wait(self.period)


def test_floods_leave_estimates_memory_logs_and_speed_intact(tmp_path):
    run_id = "flood-" + str(int(time.time() * 1000) % 10 ** 8)
    spec = RunSpec("dynamic", "diskf", run_id=run_id)
    ids = [a.id for a in spec.load(TICKS).agents]
    keys = Keys(run_id)
    rng = np.random.default_rng(11)
    sampler = RssSampler(run_id)
    proc = subprocess.Popen(up_argv(tmp_path, run_id), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    injector = None
    try:
        sampler.start()
        # the world's port, from its command line
        wait_until(lambda: any("sim.world" in a for a in processes_of(run_id).values()), 30, proc)
        world_argv = next(a for a in processes_of(run_id).values() if "sim.world" in a)
        endpoint = world_argv[world_argv.index("--listen") + 1]
        wait_until(lambda: listening(endpoint), 60, proc)
        injector = Injector(endpoint, run_id)

        # before tick 1: 1 MB messages naming tick 1, under every agent's id, to every agent
        big = [msgpack.packb({"v": wire.SCHEMA, "k": "msg", "run": run_id, "s": i, "t": 1, "pad": b"\0" * (1 << 20)})
               for i in ids]
        wait_until(lambda: injector.peers() >= 2, 60, proc)  # the world and a first agent
        before = 0
        while injector.tick == 0 and before < BIG_BEFORE:
            injector.put(keys.msg(ids[before % len(ids)], to=ids), big[before % len(ids)])
            before += 1
            time.sleep(0.02)
        wait_until(lambda: injector.tick >= PRE[1], RUN_TIMEOUT_S, proc)
        rss_before = dict(sampler.last)
        assert len(rss_before) == len(ids)

        # mid-run: every millisecond a few garbage payloads under random ids; a 130k-key map every
        # 200 ms (under a real id or a random one); a world tick far ahead or beyond the run every 20 ms
        garbage = [rng.bytes(int(n)) for n in rng.integers(1, 300, 64)]
        huge_map = msgpack.packb({str(i): 0 for i in range(130_000)})
        flood_start = last_map = last_tick = time.monotonic()
        n = 0
        while time.monotonic() - flood_start < FLOOD_S and injector.tick < TICKS - 600:
            for _ in range(3):
                n += 1
                injector.put(f"{keys.root}/agent/{int(rng.integers(10, 2 ** 62))}/msg/{address(ids)}",
                             garbage[n % 64])
            now = time.monotonic()
            if now - last_map > 0.2:
                last_map = now
                injector.put(keys.msg(ids[n % len(ids)] if n % 2 else 10 ** 9 + n, to=ids), huge_map)
            if now - last_tick > 0.02 and injector.last_tick is not None:
                last_tick = now
                doc = msgpack.unpackb(injector.last_tick)
                # far enough ahead that it is never k + 1 of an agent, even if the injector lags the world
                far = doc["t"] + int(rng.integers(200, 10 ** 6)) if n % 2 else TICKS + 1 + n
                injector.put(keys.tick, msgpack.packb({**doc, "t": far}))
            time.sleep(0.001)
        flood_end_tick = injector.tick
        flood_s = time.monotonic() - flood_start
        rss_flood = {p: sampler.peak[p] for p in rss_before}

        out, err = proc.communicate(timeout=RUN_TIMEOUT_S)
    finally:
        sampler.done.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if injector is not None:
            injector.close()

    res = json.loads((tmp_path / "results.json").read_text()) if (tmp_path / "results.json").exists() else {}
    row = res.get("diskf", {}).get("range=120", {})
    rejected = {}  # what the agents refused (their last reports' counters)
    for c in row.get("counters", {}).values():
        for r, k in c["rejected"].items():
            rejected[r] = rejected.get(r, 0) + k
    growth = {p: rss_flood[p] - rss_before[p] for p in rss_before}
    peak = max(sampler.peak.values())
    logs = {f.name: f.stat().st_size for f in (tmp_path / "logs").iterdir()}
    seen = injector.seen
    before_rate = rate(seen, *PRE)
    # the windows after the flood: the best one counts (the machine is shared, and one window
    # may fall on someone else's burst)
    after = [rate(seen, s, s + WINDOW) for s in range(flood_end_tick + 50, TICKS - WINDOW + 1, WINDOW)
             if s in seen and s + WINDOW in seen]
    during = rate(seen, PRE[1], flood_end_tick) if flood_end_tick > PRE[1] else 0.0
    print(f"\nflood: {injector.sent} payloads ({before} of 1 MB before tick 1, then {flood_s:.1f} s); ticks/s "
          f"before {before_rate:.0f}, during {during:.0f}, after {max(after, default=0):.0f} "
          f"(windows {[round(a) for a in after]}); agent RSS before the flood "
          f"{min(rss_before.values()):.0f}-{max(rss_before.values()):.0f} MB, growth under it at most "
          f"{max(growth.values()):.1f} MB, peak of the run {peak:.0f} MB; logs at most {max(logs.values())} bytes; "
          f"rejected {rejected}; up exit {proc.returncode}")

    # exit status and the results: every agent-tick reported
    assert proc.returncode == 0, err[-2000:]
    assert row["missing_ticks"] == {} and row["complete"] is True
    # the estimates: bit for bit the engine's (assert_same also checks every agent-tick was reported)
    est = json.loads((tmp_path / "estimates.json").read_text())
    _, ref = reference(spec, TICKS, SEED)
    assert_same(est, ref, tol=0.0)
    # the flood reached the agents and was refused, counted
    assert rejected.get("unknown-sender", 0) > 1000 and rejected.get("size", 0) > 10, rejected
    assert rejected.get("tick-future", 0) > 10, rejected
    # memory: bounded, before tick 1 and under the flood
    assert max(growth.values()) < RSS_GROWTH_MB, (rss_before, rss_flood)
    assert peak < RSS_MAX_MB, sampler.peak
    # logs: a few lines, whatever was sent
    assert max(logs.values()) < LOG_BYTES, logs
    # speed: back within 20 % of the same run's before the flood
    assert all(t in seen for t in range(PRE[0], TICKS + 1)), "the injector missed ticks"
    assert after and max(after) >= 0.8 * before_rate, (before_rate, after)
