"""The seeded per-link fault model, the delay line and the inbox, without zenoh."""
from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from diskf_mesh.mesh.wire.counters import Counters, total
from diskf_mesh.mesh.protocol.delayline import DelayLine
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.faults import PERFECT, FaultConfig, FaultModel, add_arguments, from_args
from diskf_mesh.mesh.protocol.receive import Inbox

ALL = FaultConfig(loss=0.2, latency_ms=5, jitter_ms=5, duplicate=0.05, reorder=0.05)


def plans(model, links, ticks):
    return {(s, r, k): model.plan(s, r, k) for s, r in links for k in ticks}


def test_same_seed_same_faults_whatever_the_order():
    links = [(s, r) for s in range(1, 5) for r in range(1, 5) if s != r]
    a = plans(FaultModel(ALL, seed=7), links, range(1, 150))
    b = FaultModel(ALL, seed=7)  # queried in another order, with ticks skipped
    for (s, r, k) in sorted(a, key=lambda t: (-t[2], t[1], t[0])):
        if k % 3:
            assert b.plan(s, r, k) == a[(s, r, k)]
    c = plans(FaultModel(ALL, seed=8), links, range(1, 150))
    assert a != c


def test_links_are_independent_streams():
    m = FaultModel(ALL, seed=1)
    assert [m.plan(1, 2, k) for k in range(100)] != [m.plan(2, 1, k) for k in range(100)]


@pytest.mark.parametrize("loss", [0.0, 0.1, 0.3, 0.5, 1.0])
def test_loss_rate(loss):
    m = FaultModel(FaultConfig(loss=loss), seed=3)
    n = 20000
    lost = sum(not m.plan(s, 9, k) for s in range(1, 5) for k in range(n // 4))
    assert abs(lost / n - loss) < 4 * np.sqrt(loss * (1 - loss) / n) + 1e-12


def test_delays_duplicates_and_reordering():
    cfg = FaultConfig(latency_ms=5, jitter_ms=3, duplicate=0.2, reorder=0.1, reorder_ms=40)
    m = FaultModel(cfg, seed=11)
    all_copies = [m.plan(1, 2, k) for k in range(20000)]
    assert all(len(p) in (1, 2) for p in all_copies)          # nothing lost at loss 0
    dup = np.mean([len(p) == 2 for p in all_copies])
    assert abs(dup - 0.2) < 0.02
    copies = [d for p in all_copies for d in p]
    plain = np.array([d.delay_s for d in copies if not d.reordered]) * 1000
    held = np.array([d.delay_s for d in copies if d.reordered]) * 1000
    assert plain.min() >= 2.0 and plain.max() <= 8.0
    assert abs(plain.mean() - 5.0) < 0.1
    assert held.min() >= 42.0 and held.max() <= 48.0
    assert abs(len(held) / len(copies) - 0.1) < 0.01
    assert {d.copy for d in copies} == {0, 1}


def test_jitter_never_gives_a_negative_delay():
    m = FaultModel(FaultConfig(latency_ms=1, jitter_ms=10), seed=0)
    assert min(d.delay_s for k in range(2000) for d in m.plan(1, 2, k)) == 0.0


def test_no_faults_is_the_perfect_link():
    m = FaultModel(FaultConfig(), seed=0)
    assert not FaultConfig().active
    assert all(m.plan(1, 2, k) is PERFECT for k in range(10))


@pytest.mark.parametrize("table, field", [
    ({"loss": 1.5}, "faults.loss"), ({"loss": -0.1}, "faults.loss"), ({"latency_ms": float("inf")}, "faults.latency_ms"),
    ({"jitter_ms": "5"}, "faults.jitter_ms"), ({"lossy": 0.1}, "faults.lossy"), ({"duplicate": True}, "faults.duplicate"),
])
def test_bad_fault_settings_name_the_field(table, field):
    with pytest.raises(InputError) as e:
        FaultConfig.from_mapping(table)
    assert e.value.field == field


def test_command_line_overrides_the_scenario_field_by_field():
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--loss", "0.3", "--jitter-ms", "2"])
    cfg = from_args(args, {"loss": 0.1, "latency_ms": 5.0, "reorder": 0.05})
    assert cfg == FaultConfig(loss=0.3, latency_ms=5.0, jitter_ms=2.0, reorder=0.05)
    again = from_args(p.parse_args(cfg.to_argv()), {})
    assert again == cfg
    for bad in (["--loss", "2"], ["--latency-ms", "-1"], ["--reorder", "nan"]):
        with pytest.raises(SystemExit):
            p.parse_args(bad)


def test_scenario_faults_table_is_read():
    from diskf_mesh.data.scenario import parse_scenario
    raw = {"model": {"G": [[1.0], [1.0]], "dynamics": "rotation", "Q": [[1, 0], [0, 1]], "P0": [[1, 0], [0, 1]],
                     "x0": [0, 0]},
           "agents": [{"id": 1, "H": [[1, 0]], "R": [[1]]}], "faults": {"loss": 0.25, "latency_ms": 3}}
    assert from_args(argparse.Namespace(), parse_scenario(raw).faults) == FaultConfig(loss=0.25, latency_ms=3.0)


# --------------------------------------------------------------------------
# delay line
# --------------------------------------------------------------------------
def test_delay_line_gives_copies_in_due_order_and_what_is_in_flight():
    line = DelayLine()
    assert line.next_at == math.inf and line.due(1e9) == []
    for item, at in [("c", 10.06), ("a", 10.02), ("b", 10.04), ("a2", 10.02), ("never", 15.0)]:
        line.push(item, at)
    assert line.next_at == 10.02 and line.in_flight == 5
    assert line.due(10.01) == []
    assert line.due(10.04) == ["a", "a2", "b"]      # due order, ties in push order
    assert line.due(10.06) == ["c"]
    assert line.drain() == ["never"] and line.in_flight == 0


# --------------------------------------------------------------------------
# inbox
# --------------------------------------------------------------------------
def test_inbox_fuses_a_duplicate_once_and_counts_late_and_unlinked():
    c = Counters()
    box = Inbox(c)
    assert box.offer(3, 1, "m3") == "held"
    assert box.offer(1, 1, "m1") == "held"
    assert box.offer(3, 1, "m3 again") == "duplicate"
    assert box.offer(2, 1, "m2") == "held"
    assert box.offer(2, 2, "next") == "held"
    assert box.take(1, linked={1, 3}) == [(1, "m1"), (3, "m3")]  # by sender id; 2 out of range
    assert box.offer(4, 1, "too late") == "late"
    assert box.offer(4, 1, "too late again") == "duplicate"
    assert box.take(3, linked={2}) == []       # tick 2 was skipped: its message is late
    box.close()
    assert box.offer(5, 9, "after the end") == "late"
    assert (c.arrived, c.duplicate, c.fused, c.unlinked, c.late) == (8, 2, 2, 1, 3)
    c.sent, c.received, c.lost = 7, 6, 1
    assert c.imbalance() == []


def test_counters_round_trip_and_sum():
    a = Counters(published=3, sent=5, lost=1, received=4, fused=3, late=1)
    a.reject("not-spd")
    a.reject("tick-past", 2)
    assert Counters.from_dict(a.to_dict()) == a
    assert a.to_json()["rejected"] == {"not-spd": 1, "tick-past": 2}
    s = total([a, a])
    assert (s.sent, s.rejected) == (10, {"not-spd": 2, "tick-past": 4})
    assert Counters(sent=2, received=1, arrived=1).imbalance() == [
        "sent 2 != received 1 + lost 0", "arrived 1 != fused 0 + late 0 + unlinked 0 + duplicate 0"]


def test_delivered_links_follow_the_link_plans():
    from diskf_mesh.data.faults import delivered_links
    K, N, ids = 30, 4, (3, 5, 8, 9)
    links = np.ones((K, N, N), dtype=bool)
    links[:, 0, 3] = links[:, 3, 0] = False
    cfg = FaultConfig(loss=0.3, latency_ms=10, jitter_ms=10)
    got = delivered_links(links, ids, cfg, seed=4, deadline_s=0.012)
    m = FaultModel(cfg, seed=4)
    for k in range(1, K + 1):
        for r in range(N):
            assert got[k - 1, r, r]
            for s in range(N):
                if r != s:
                    plan = m.plan(ids[s], ids[r], k)
                    want = links[k - 1, r, s] and bool(plan) and plan[0].delay_s < 0.012
                    assert got[k - 1, r, s] == want
    assert not got[:, 0, 3].any()
    assert np.array_equal(delivered_links(links, ids, FaultConfig(), seed=4), links)
