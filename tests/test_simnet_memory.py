"""What a simulated run holds grows with what it needs, not with N^2 or a
Python object per delivery: a tick's messages are decoded once for all
their receivers however many agents there are, an agent remembers a closed
tick by its linked set, and the world's record of who fused whom and of
the digests grows with the messages fused (``engine.fused.FusedSets``),
reading as the dense record it stands for."""
from __future__ import annotations

import tracemalloc

import numpy as np

import simnet_cases as cases

from diskf_mesh.engine.fused import tick_digests
from diskf_mesh.mesh.protocol import shared
from diskf_mesh.mesh.protocol.receive import Inbox
from diskf_mesh.mesh.protocol.reports import RunReports
from diskf_mesh.mesh.protocol.world_machine import WorldMachine
from diskf_mesh.mesh.simulated.simrun import simulate_run
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.keys import Keys


def _allocated(make) -> tuple:
    """(what ``make()`` returned, the bytes it left allocated)."""
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        out = make()
        return out, tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()


def test_a_message_is_decoded_once_for_all_its_receivers_with_more_agents_than_the_memo_keeps(monkeypatch):
    """The decodes shared by a payload's receivers are kept for two per
    agent: with fewer kept than a tick's messages, a message evicted before
    its last receivers read it would be decoded (and held) once per receiver."""
    monkeypatch.setattr(shared, "KEEP", 4)
    decode, calls = wire.decode, []
    monkeypatch.setattr(wire, "decode", lambda payload, **kw: (calls.append(payload), decode(payload, **kw))[1])
    scn, trace = cases.world("random-geometric", 30, 4, 1)
    run = simulate_run(scn, trace, "diskf", 1)
    published = sum(m.counters.published for pid, m in run.outcome.machines.items() if pid.startswith("agent"))
    assert run.status.status == "exact" and published == 30 * 4
    assert len(calls) > published / 2 and len(calls) == len(set(calls))  # each message read once, if at all


def test_a_closed_tick_is_remembered_by_its_linked_set_not_by_a_set_per_tick():
    """An agent's inbox remembers who came at each of ``keep`` closed ticks
    (to tell a duplicate from a late copy) as the linked set it was taken
    with, the same set tick after tick, and the few that did not come."""
    senders = frozenset(range(1, 2001))
    box = Inbox(keep=16)

    def run(ticks):
        for t in ticks:
            box.hold(t, dict.fromkeys(senders - {7}, "m"))
            box.take(t, senders)

    run(range(1, 21))  # the window filled (and the interpreter's free lists)
    _, kept = _allocated(lambda: run(range(21, 41)))
    assert kept < 16 * 1024, kept  # a set of 2,000 senders per closed tick would be 64 KiB each
    assert box.offer(5, 40, "again") == "duplicate" and box.offer(7, 40, "at last") == "late"
    assert box.offer(7, 40, "again") == "duplicate" and box.offer(9999, 40, "unlinked") == "late"
    c = box.counters
    assert (c.fused, c.duplicate, c.late, c.unlinked) == (40 * 1999, 2, 2, 0)


def test_the_worlds_record_grows_with_the_messages_fused_not_with_ticks_times_n_squared():
    """2,000 agents x 20 ticks, each fusing 10 senders' messages: a dense
    record of who fused whom would be 80 MB, a digest object per message
    400,000 of them; the world's record holds 2 bytes per message fused and
    one digest per (tick, sender)."""
    N, K, J = 2000, 20, 10
    scn, trace = cases.world("random-geometric", N, K, 0)
    ids = scn.ids
    digest = {(t, s): wire.digest(bytes([t]) + s.to_bytes(2, "little")) for t in range(1, K + 1) for s in ids}

    def note():
        world = WorldMachine(scn, trace, "diskf", 0, Keys("mem"), "n")
        for t in range(1, K + 1):
            for i in range(N):
                senders = [ids[(i + d) % N] for d in range(1, J + 1)]
                world.record.note_fused(t, i, senders, (), [digest[(t, s)] for s in senders], world._index)
        return world

    world, kept = _allocated(note)
    assert kept < 32 * 2**20, kept / 2**20  # dense: 95 MB
    rec = world.record
    assert int(np.asarray(rec.fused).sum()) == N * K * J
    senders, values = rec.claimed_digests()[(3, 5)]
    assert senders.tolist() == list(range(6, 16))
    assert values.tolist() == [int.from_bytes(digest[(3, ids[s])], "little") for s in range(6, 16)]


def test_the_sparse_record_reads_as_the_dense_one():
    """The same reports noted in a sparse record (the world's) and a dense
    one (a recording's) read the same: who fused whom, tick by tick and as
    a whole, and every digest as reported: one the others did not report
    for its sender (a forged copy), a report naming a sender twice, an id
    not in the run, a receiver noted twice."""
    N, K = 12, 4
    ids = [f"a{j}" for j in range(N)]
    index = {a: j for j, a in enumerate(ids)}
    rng = np.random.default_rng(3)
    sparse, dense = RunReports(**RunReports.empty(K, N, 2, 1, sparse=True)), RunReports(**RunReports.empty(K, N, 2, 1))
    sent = {(t, a): wire.digest(f"{t}{a}".encode()) for t in range(1, K + 1) for a in ids}
    notes = []
    for t in range(1, K + 1):
        for i in range(N):
            fused = [ids[j] for j in sorted(rng.choice(N, size=int(rng.integers(0, 6)), replace=False))]
            digests = [sent[(t, a)] for a in fused]
            if fused and (t, i) == (2, 3):
                digests[0] = wire.digest(b"forged")
            if (t, i) == (3, 4):
                fused, digests = ["a1", "nobody", "a1"], [sent[(t, "a1")], b"x" * 8, sent[(t, "a1")]]
            notes.append((t, i, fused, (), digests))
    notes.append((1, 2, ["a5"], (), [sent[(1, "a5")]]))  # the same receiver and tick again
    for note in notes:
        sparse.note_fused(*note, index)
        dense.note_fused(*note, index)
    assert np.array_equal(np.asarray(sparse.fused), dense.fused)
    assert all(np.array_equal(sparse.fused[t], dense.fused[t]) for t in range(K))
    assert np.array_equal(np.asarray(sparse.fused[:2]), dense.fused[:2])
    assert [sparse.fused.receivers(1, j) for j in range(N)] == [np.flatnonzero(dense.fused[1, :, j]).tolist()
                                                                 for j in range(N)]

    def triples(said):
        return sorted(zip(*(a.tolist() for a in said)))

    for k in range(1, K + 1):
        assert triples(sparse.tick_digests(k)) == triples(dense.tick_digests(k))
        assert triples(tick_digests(sparse.claimed_digests(), k)) == triples(tick_digests(dense.claimed_digests(), k))
    claimed = {key: sorted(zip(s.tolist(), g.tolist())) for key, (s, g) in dense.claimed_digests().items()}
    assert {key: sorted(zip(s.tolist(), g.tolist())) for key, (s, g) in sparse.claimed_digests().items()} == claimed
    forged = dict(zip(*(a.tolist() for a in sparse.claimed_digests()[(2, 3)])))
    assert wire.digest(b"forged") in {v.to_bytes(8, "little") for v in forged.values()}
