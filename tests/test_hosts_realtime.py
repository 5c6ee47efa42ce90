"""Real time over hosts: ``up --hosts FILE --rate HZ --deadline-ms MS`` gives
the rate to the world and, through every host's shard (``diskf-mesh
host``), the rate and the deadline to every agent; ``host`` refuses a
deadline without a rate."""
from __future__ import annotations

import pytest

from diskf_mesh.cli import main as cli
from mesh_helpers import up
from sim.launcher import free_port

pytestmark = pytest.mark.mesh


def test_host_refuses_a_deadline_without_a_rate(capsys):
    argv = ["host", "--run-id", "r1", "--agents", "1-4", "--connect", "tls/127.0.0.1:9", "--insecure",
            "--deadline-ms", "50"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: deadline-ms"), err


def test_up_hosts_runs_in_real_time_with_every_agents_deadline(tmp_path):
    """Two hosts on loopback, a router each. Latency past the deadline:
    every agent fuses at its deadline and so misses every neighbour's
    message (an agent without the deadline would wait for them and fuse
    them), and the run completes at its rate."""
    ticks, rate = 20, 10.0
    world, router_a, router_b = free_port(), free_port(), free_port()
    hosts = tmp_path / "hosts.toml"
    hosts.write_text(f'[world]\nlisten = "tls/127.0.0.1:{world}"\n'
                     f'[hosts.a]\nagents = "1-4"\nrouter = "tls/127.0.0.1:{router_a}"\n'
                     f'[hosts.b]\nagents = "5-9"\nrouter = "tls/127.0.0.1:{router_b}"\n')
    done, doc, res = up(tmp_path, "--hosts", str(hosts), "--scenario", "dynamic", "--ticks", str(ticks),
                        "--rate", str(rate), "--deadline-ms", "10", "--latency-ms", "35", "--max-miss-rate", "1",
                        timeout=300)
    assert done.returncode == 0, done.stderr
    row = next(iter(next(iter(res.values())).values()))
    assert row["complete"] is True
    assert row["rate_hz"] == rate and row["deadline_s"] == pytest.approx(0.010)
    assert row["tick_period"]["ticks"] == ticks
    assert row["tick_period"]["mean_s"] == pytest.approx(1 / rate, rel=0.25)
    dm = row["deadline_misses"]
    assert dm["messages"] == dm["messages_due"] > 0
    assert len(dm["per_agent"]) == 9 and all(a["messages"] == a["messages_due"] > 0
                                             for a in dm["per_agent"].values())
    assert all(s == [] for tick in doc["fused"] for s in tick)
