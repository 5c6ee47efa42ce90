"""Real-time mode (``--rate``, ``diskf_mesh.mesh.protocol.clock``): the world ticks on
the wall clock, agents fuse what arrived by their deadline, misses are
counted, and the record of what was fused replays the run bit for bit.
Lockstep (no ``--rate``) is the engine bit for bit: test_mesh_equivalence."""
from __future__ import annotations

import json

import numpy as np
import pytest

from diskf_mesh.cli import main as cli
from diskf_mesh.core import exits
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.engine import batch as engine
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.recording import reader
from diskf_mesh.recording.replay import compare, replay
from mesh_helpers import MESH_ALGORITHM, reference, up


SPEC = RunSpec("dynamic", MESH_ALGORITHM)


def row_of(res: dict) -> dict:
    return next(iter(next(iter(res.values())).values()))


def fused_links(doc: dict) -> np.ndarray:
    """(K, N, N) [tick - 1, receiver, sender] from the estimates document's
    ``fused`` lists, the diagonal set (an agent fuses its own message)."""
    ids = doc["ids"]
    K, N = len(doc["fused"]), len(ids)
    links = np.zeros((K, N, N), dtype=bool)
    links[:, np.arange(N), np.arange(N)] = True
    for k, tick in enumerate(doc["fused"]):
        for r, senders in enumerate(tick):
            for s in senders:
                links[k, r, ids.index(s)] = True
    return links


def assert_bitwise(doc: dict, est: engine.Estimates) -> None:
    assert np.array(doc["reported"]).all()
    np.testing.assert_array_equal(np.array(doc["x"], dtype=float), est.x[0])
    np.testing.assert_array_equal(np.array(doc["P"], dtype=float), est.P[0])
    valid = np.array([[row is not None for row in tick] for tick in doc["d"]])
    np.testing.assert_array_equal(valid, est.d_valid[0])


def replayed(doc: dict, ticks: int, seed: int = 0) -> engine.Estimates:
    """The engine on the run's trace with exactly the fused sets the document records."""
    trace, _ = reference(SPEC, ticks, seed)
    return engine.run(trace.with_links(fused_links(doc)[None]), SPEC.algorithm, SPEC.load(ticks).params)


def test_realtime_run_keeps_its_rate_and_replays_bit_for_bit(tmp_path):
    ticks, rate = 40, 20.0
    mcap = tmp_path / "run.mcap"
    done, doc, res = up(tmp_path, "--scenario", "dynamic", "--ticks", str(ticks), "--rate", str(rate),
                        "--record", str(mcap), "--max-miss-rate", "1", timeout=300)  # a loaded machine misses
    assert done.returncode == 0, done.stderr
    row = row_of(res)
    period = row["tick_period"]
    assert period["ticks"] == ticks
    # the world opened its ticks on the clock: tick 1 to the end of tick K within 25 % of K / rate
    span = period["mean_s"] * (ticks - 1) + 1.0 / rate
    assert abs(span - ticks / rate) <= 0.25 * ticks / rate, period
    dm = row["deadline_misses"]
    assert dm["reports_due"] == ticks * 9 and dm["messages_due"] > 0
    assert dm["total"] == dm["messages"] + dm["reports"] == sum(a["total"] for a in dm["per_agent"].values())
    assert row["complete"]
    # the run checked itself: messages fused late are accepted degradation (within --max-miss-rate), counted
    assert row["status"] in ("exact", "degraded") and row["evidence"]["differing"] == 0, row["reason"]
    assert row["evidence"]["degraded"]["messages"] == (dm["messages"] if row["status"] == "degraded" else 0)
    # the estimates document's fused sets reproduce every estimate bit for bit ...
    assert_bitwise(doc, replayed(doc, ticks))
    # ... and so does the recording's (diskf-mesh replay RUN.mcap)
    rec = reader.read(mcap)
    assert compare(rec, replay(rec)).equal
    np.testing.assert_array_equal(rec.fused, fused_links(doc))


def test_latency_past_the_deadline_is_missed_never_fused(tmp_path):
    """Link delays of 0-20 ms against a 10 ms deadline: a message whose
    every copy is due after the deadline is never fused (the latency runs
    from when the receiver has the tick, as its deadline does); the rest
    may be. The run completes with the misses counted."""
    ticks, rate, deadline_ms = 30, 20.0, 10.0
    faults = FaultConfig(latency_ms=10.0, jitter_ms=10.0)
    done, doc, res = up(tmp_path, "--scenario", "dynamic", "--ticks", str(ticks), "--rate", str(rate),
                        "--deadline-ms", str(deadline_ms), "--latency-ms", "10", "--jitter-ms", "10",
                        "--max-miss-rate", "1", timeout=300)
    assert done.returncode == 0, done.stderr
    row = row_of(res)
    assert row["complete"]
    ids, links = doc["ids"], fused_links(doc)
    model = FaultModel(faults, 0)
    trace, _ = reference(SPEC, ticks, 0)
    late = in_time = fused_late = 0
    for k in range(1, ticks + 1):
        for r, receiver in enumerate(ids):
            for s, sender in enumerate(ids):
                if r == s or not trace.links[0, k - 1, r, s]:
                    continue
                due = min(d.delay_s for d in model.plan(sender, receiver, k))
                if due > deadline_ms / 1000.0:
                    late += 1
                    fused_late += bool(links[k - 1, r, s])
                else:
                    in_time += 1
    assert late > 0 and in_time > 0
    assert fused_late == 0, "a message due after the deadline was fused"
    assert row["deadline_misses"]["messages"] >= late
    assert_bitwise(doc, replayed(doc, ticks))
    assert_cli_replays(tmp_path, doc, ticks)


def assert_cli_replays(tmp_path, doc: dict, ticks: int) -> None:
    """``diskf-mesh replay TRACE --fused EST``: the run's trace (``simulate``,
    same scenario, seed and ticks) on the document's fused sets gives every
    estimate bit for bit (exit 0); fused sets changed, or a trace of
    another seed, and it says the run diverged (``exits.DIVERGED``)."""
    trace = tmp_path / "trace.json"
    assert cli.main(["simulate", "--scenario", "dynamic", "--ticks", str(ticks), "--out", str(trace)]) == 0
    est, out = tmp_path / "estimates.json", tmp_path / "replayed.json"
    assert json.loads(est.read_text()) == doc
    assert cli.main(["replay", str(trace), "--fused", str(est), "--out", str(out)]) == 0
    again = json.loads(out.read_text())
    assert again["x"] == doc["x"] and again["P"] == doc["P"] and again["d"] == doc["d"]
    # the neighbours' messages fused after tick 10 dropped from the record: the replay differs from the run
    bent = json.loads(json.dumps(doc))
    bent["fused"][10:] = [[[s for s in senders if s == i] for i, senders in zip(doc["ids"], tick)]
                          for tick in doc["fused"][10:]]
    assert bent["fused"] != doc["fused"]
    (tmp_path / "bent.json").write_text(json.dumps(bent))
    assert cli.main(["replay", str(trace), "--fused", str(tmp_path / "bent.json")]) == exits.DIVERGED
    other = tmp_path / "seed1.json"
    assert cli.main(["simulate", "--scenario", "dynamic", "--ticks", str(ticks), "--seed", "1", "--out", str(other)]) == 0
    assert cli.main(["replay", str(other), "--fused", str(est)]) == exits.DIVERGED


def test_every_message_late_fuses_nothing_and_completes(tmp_path):
    """Latency far past the deadline: every neighbour's message is a miss,
    each agent fuses only its own message (the engine with no links), and
    the run still completes at its rate."""
    ticks, rate = 20, 20.0
    done, doc, res = up(tmp_path, "--scenario", "dynamic", "--ticks", str(ticks), "--rate", str(rate),
                        "--deadline-ms", "10", "--latency-ms", "35", "--max-miss-rate", "1", timeout=300)
    assert done.returncode == 0, done.stderr
    dm = row_of(res)["deadline_misses"]
    assert dm["messages"] == dm["messages_due"] > 0
    # accepted, but said: one warning line with the count
    warned = [ln for ln in done.stderr.splitlines() if ln.startswith("warning: real time:")]
    assert len(warned) == 1 and f"{dm['total']} deadline misses" in warned[0], done.stderr
    assert all(s == [] for tick in doc["fused"] for s in tick)
    trace, ref = reference(SPEC, ticks, 0)
    alone = engine.run(trace.with_links(np.broadcast_to(np.eye(9, dtype=bool), trace.links.shape).copy()),
                       SPEC.algorithm, SPEC.load(ticks).params)
    assert_bitwise(doc, alone)
    assert not np.array_equal(alone.x, ref.x)  # fusing nothing is not the lockstep run


def test_a_run_that_did_not_keep_up_fails_by_default(tmp_path):
    """No --max-miss-rate: more than MAX_MISS_RATE of the deadlines missed
    (here every neighbour's message) is exit TOO_MANY_MISSES with one line,
    the results still written."""
    done, doc, res = up(tmp_path, "--scenario", "dynamic", "--ticks", "10", "--rate", "20",
                        "--deadline-ms", "10", "--latency-ms", "35", timeout=300)
    assert done.returncode == realtime.TOO_MANY_MISSES, done.stderr
    dm = row_of(res)["deadline_misses"]
    assert dm["miss_rate"] > realtime.MAX_MISS_RATE and dm["messages"] == dm["messages_due"] > 0
    err = [ln for ln in done.stderr.strip().splitlines() if ln.startswith(("error", "warning"))]
    assert len(err) == 1 and err[0].startswith("error: ") and "--max-miss-rate 0.05" in err[0], done.stderr


def test_max_miss_rate_fails_the_run(tmp_path):
    done, doc, res = up(tmp_path, "--scenario", "dynamic", "--ticks", "10", "--rate", "20",
                        "--deadline-ms", "10", "--latency-ms", "35", "--max-miss-rate", "0.5", timeout=300)
    assert done.returncode == 4, done.stderr
    assert row_of(res)["deadline_misses"]["miss_rate"] > 0.5
    assert done.stderr.strip().splitlines()[-1].startswith("error: ")


@pytest.mark.parametrize("flags", [["--deadline-ms", "10"], ["--rate", "10", "--deadline-ms", "100"],
                                   ["--rate", "0"], ["--max-miss-rate", "0.1"]])
def test_bad_realtime_flags_exit_2(tmp_path, flags):
    done, _, _ = up(tmp_path, "--scenario", "dynamic", "--ticks", "5", *flags, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().startswith("error: ") and len(done.stderr.strip().splitlines()) == 1
