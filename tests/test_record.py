"""Recordings: ``up --record`` -> ``inspect`` -> ``replay`` equals
the run bit for bit, for every estimator, with and without faults; the
verdict of every message agrees with the agents' counters and the seeded
fault layer; ``figures --from`` draws the run."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from diskf_mesh import estimators as algorithms
from diskf_mesh.mesh.wire.counters import Counters
from diskf_mesh.data.faults import FaultConfig, FaultModel
from diskf_mesh.recording.reader import read

from mesh_helpers import up

pytestmark = pytest.mark.mesh

TICKS = 30
SEED = 5


def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", *map(str, args)], capture_output=True,
                          text=True, timeout=120)


def recorded_run(tmp_path, algorithm: str, *flags) -> tuple:
    """(recording path, the world's estimates doc) of one ``up --record``."""
    path = tmp_path / "run.mcap"
    done, est, _ = up(tmp_path, "--scenario", "dynamic", "--algorithm", algorithm, "--ticks", str(TICKS),
                      "--seed", str(SEED), "--record", str(path), *flags)
    assert done.returncode == 0, done.stderr
    return path, est


def assert_estimates_equal(doc: dict, ref: dict) -> None:
    """Two diskf-estimates documents hold the same bits (x, P, d)."""
    for key in ("x", "P"):
        a, b = np.array(doc[key], dtype=float), np.array(ref[key], dtype=float)
        assert a.shape == b.shape and np.array_equal(a, b), key
    assert doc["d"] == ref["d"]


@pytest.mark.parametrize("loss", [0.0, 0.3])
@pytest.mark.parametrize("algorithm", algorithms.NAMES)
def test_record_inspect_replay_bit_for_bit(tmp_path, algorithm, loss):
    flags = ["--loss", str(loss)] if loss else []
    path, est = recorded_run(tmp_path, algorithm, *flags)

    # the recording holds exactly what the world received
    rec = read(path)
    assert rec.finished and rec.ticks == TICKS and rec.reported.all()
    np.testing.assert_array_equal(rec.x, np.array(est["x"], dtype=float))
    np.testing.assert_array_equal(rec.P, np.array(est["P"], dtype=float))

    # inspect: counts by verdict agree with the agents' own counters
    done = cli("inspect", path, "--json")
    assert done.returncode == 0, done.stderr
    s = json.loads(done.stdout)
    assert (s["ticks"], s["agents"], s["algorithm"], s["status"]) == (TICKS, 9, algorithm, "done")
    assert s["reported"] == s["agent_ticks"] == 9 * TICKS
    assert s["messages"]["sent"] == 9 * TICKS          # the world heard every agent message
    last = {int(i): Counters.from_dict(c) for i, c in est["agent_counters"].items()}
    delivered = s["messages"]["delivered"]
    assert delivered["fused"] == sum(c.fused for c in last.values())
    assert delivered["lost"] == sum(c.lost for c in last.values())
    assert delivered["late"] == delivered["rejected"] == delivered["unreported"] == 0
    assert (delivered["lost"] > 0) == (loss > 0)
    assert s["metrics"]["mae_state"] == pytest.approx(est["metrics"]["mae_state"], rel=1e-12)

    # replay: the engine on what each agent fused gives the recorded bits
    out = tmp_path / "replayed.json"
    done = cli("replay", path, "--out", out)
    assert done.returncode == 0, done.stdout + done.stderr
    assert_estimates_equal(json.loads(out.read_text()), est)


def test_every_verdict_is_the_fault_layers(tmp_path):
    """Lossy and duplicating links: a message is lost exactly where the
    seeded fault layer drops it, and each duplicate copy is on record."""
    path, est = recorded_run(tmp_path, "diskf", "--loss", "0.3", "--duplicate", "0.3")
    rec = read(path)
    model = FaultModel(FaultConfig(loss=0.3, duplicate=0.3), SEED)
    assert rec.delivered
    for doc in rec.delivered:
        plan = model.plan(doc["sender"], doc["receiver"], doc["tick"])
        assert doc["copies"] == len(plan)
        assert (doc["verdict"] == "lost") == (not plan), doc
        assert doc["verdict"] in ("fused", "lost"), doc
    last = {int(i): Counters.from_dict(c) for i, c in est["agent_counters"].items()}
    dup = sum(doc["copies"] - 1 for doc in rec.delivered if doc["copies"] > 1)
    assert dup == sum(c.duplicate for c in last.values()) > 0
    # every message of every channel is valid against its channel's JSON Schema
    jsonschema = pytest.importorskip("jsonschema")
    from diskf_mesh.recording import scene
    from diskf_mesh.recording.schemas import CHANNELS

    assert set(rec.messages_by_topic) == {*CHANNELS, scene.TOPIC}
    for topic, docs in rec.messages_by_topic.items():
        if topic != scene.TOPIC:
            check = jsonschema.Draft202012Validator(CHANNELS[topic])
            for doc in docs:
                check.validate(doc)
    # /scene: foxglove.SceneUpdate, decoded with the protobuf schema the file holds
    from foxglove_helpers import protobuf_decoder
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        scenes = [(schema, msg) for schema, _, msg in make_reader(f).iter_messages(topics=[scene.TOPIC])]
    assert len(scenes) == rec.ticks and scenes[0][0].encoding == "protobuf"
    decode = protobuf_decoder(scenes[0][0].name, scenes[0][0].data)
    for _, msg in scenes:
        ents = {e.id: e for e in decode(msg.data).entities}
        assert set(ents) == {"agents", "links", "truth", "estimates"} and len(ents["agents"].spheres) == len(rec.ids)
    # each agent-tick's fused senders are the receivers' "fused" verdicts
    fused = {(d["tick"], d["receiver"], d["sender"]) for d in rec.delivered if d["verdict"] == "fused"}
    where = {i: j for j, i in enumerate(rec.ids)}
    from_matrix = {(k + 1, r, s) for k, r, s in zip(*np.nonzero(rec.fused)) if r != s}
    assert {(k, where[r], where[s]) for k, r, s in fused} == from_matrix


def test_figures_from_a_recording(tmp_path):
    path, _ = recorded_run(tmp_path, "diskf", "--loss", "0.2")
    out = tmp_path / "figs"
    done = cli("figures", "--from", path, "--out", out)
    assert done.returncode == 0, done.stderr
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs == ["run-error.png", "run-links.png", "run-trajectories.png"]
    assert all((out / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and (out / p).stat().st_size > 10_000
               for p in pngs)
