"""``up --live``: the run on a foxglove-sdk WebSocket server, read by a
client speaking the Foxglove WebSocket protocol (``foxglove.sdk.v1``):
serverInfo and advertise, subscribe to every channel, binary messageData
frames, each payload decoded with the schema the server advertised (JSON
Schema for the recording's JSON channels, protobuf for ``/scene``)."""
from __future__ import annotations

import base64
import json
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from foxglove_helpers import protobuf_decoder

from diskf_mesh.recording import scene
from diskf_mesh.recording.schemas import CHANNELS
from sim.launcher import free_port

websockets = pytest.importorskip("websockets.sync.client")
from websockets.exceptions import ConnectionClosed, WebSocketException  # noqa: E402
jsonschema = pytest.importorskip("jsonschema")
ROOT = Path(__file__).resolve().parents[1]

SUBPROTOCOL = "foxglove.sdk.v1"  # foxglove-sdk 0.30; older servers: "foxglove.websocket.v1"
MESSAGE_DATA = 0x01
LIVE_TOPICS = set(CHANNELS) - {"/run/result"} | {scene.TOPIC}  # the result comes after the ticks


def decoder(ch: dict):
    if ch["encoding"] == "json":
        assert ch["schemaEncoding"] == "jsonschema"
        check = jsonschema.Draft202012Validator(json.loads(ch["schema"]))

        def decode(data: bytes):
            doc = json.loads(data)
            check.validate(doc)
            return doc
        return decode
    assert (ch["encoding"], ch["schemaEncoding"], ch["schemaName"]) == ("protobuf", "protobuf", "foxglove.SceneUpdate")
    return protobuf_decoder(ch["schemaName"], base64.b64decode(ch["schema"]))


def watch(port: int, proc, want: set, timeout: float = 120.0) -> tuple:
    """(advertised channels by topic, decoded messages by topic) until every
    topic in ``want`` sent a message and three ticks closed."""
    deadline = time.monotonic() + timeout
    while True:  # the world starts the server once the agents are up
        try:
            ws = websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=5)
            break
        except (OSError, WebSocketException):  # not listening yet, or not ready
            if proc.poll() is not None or time.monotonic() >= deadline:
                said = proc.stderr.read() if proc.poll() is not None and proc.stderr else ""
                raise AssertionError(f"the live server never listened (status {proc.poll()}): {said}")
            time.sleep(0.2)
    got, channels, subs, decode = {}, {}, {}, {}
    with ws:
        assert ws.subprotocol == SUBPROTOCOL
        info = json.loads(ws.recv(timeout=10))
        assert info["op"] == "serverInfo" and info["name"] == "diskf-mesh"
        while not (want <= set(got) and len(got.get("/world/tick", ())) >= 3):
            assert time.monotonic() < deadline, f"no messages on {want - set(got)}"
            try:
                frame = ws.recv(timeout=30)
            except ConnectionClosed:
                raise AssertionError(f"the run ended; no message on {want - set(got)}") from None
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    new = [ch for ch in msg["channels"] if ch["topic"] not in channels]
                    for ch in new:
                        channels[ch["topic"]] = ch
                        subs[len(subs) + 1] = ch["topic"]
                        decode[ch["topic"]] = decoder(ch)
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": sid, "channelId": channels[t]["id"]} for sid, t in subs.items()
                        if t in {c["topic"] for c in new}]}))
                continue
            assert frame[0] == MESSAGE_DATA
            sid, _log_time = struct.unpack_from("<IQ", frame, 1)
            topic = subs[sid]
            got.setdefault(topic, []).append(decode[topic](frame[13:]))
    return channels, got


@pytest.mark.mesh
def test_every_channel_streams_to_a_foxglove_client(tmp_path):
    port = free_port()
    cmd = [sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--ticks", "400", "--rate", "20",
           "--seed", "3", "--live", str(port), "--json", str(tmp_path / "r.json"), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        channels, got = watch(port, proc, LIVE_TOPICS)
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=60)
    assert f"ws://127.0.0.1:{port}" in err
    # the recording's channels and schemas, byte for byte
    assert set(channels) == set(CHANNELS) | {scene.TOPIC}
    for topic, schema in CHANNELS.items():
        assert json.loads(channels[topic]["schema"]) == schema
    assert base64.b64decode(channels[scene.TOPIC]["schema"]) == scene.schema()[2]
    run = got["/run"][0]  # sent again every second for a client that came late
    ids = run["ids"]
    for topic in ("/world/truth", "/world/agents", "/agents/estimates", "/agents/counters", "/world/tick"):
        ticks = [m["tick"] for m in got[topic]]
        assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks), topic
    for m in got["/agents/estimates"]:
        for e in m["estimates"]:
            assert e["agent"] in ids and len(e["P"]) == run["n"] and e["position_error"] >= 0
    for m in got["/agents/counters"]:
        assert {c["agent"] for c in m["counters"]} <= set(ids)
    for update in got[scene.TOPIC]:
        ents = {e.id: e for e in update.entities}
        assert set(ents) == {"agents", "links", "truth", "estimates"}
        assert sorted(t.text for t in ents["agents"].texts) == sorted(str(i) for i in ids)
        assert len(ents["agents"].spheres) == len(ids)


def test_the_layout_reads_channels_the_server_and_a_recording_have():
    """docs/foxglove-layout.json: every panel's topic is a channel of both,
    and every field a message path names is in that channel's schema."""
    doc = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    config = doc["configById"]
    assert config["3D!scene"]["topics"] == {scene.TOPIC: {"visible": True}}
    paths = [p["value"] for p in config["Plot!error"]["paths"]]
    paths += [c["topicPath"] for k, c in config.items() if "topicPath" in c]
    assert len(paths) >= 12
    for path in paths:
        topic, _, rest = path.partition(".")
        schema = CHANNELS[topic]
        for field in filter(None, rest.replace("[:]", "").split(".")):
            name, _, flt = field.partition("{")
            schema = schema["properties"][name]
            schema = schema.get("items", schema)
            if flt:
                assert flt.split("==")[0] in schema["properties"], path
    # the panels the layout places are the ones it configures
    placed = json.dumps(doc["layout"])
    assert all(f'"{k}"' in placed for k in config)


@pytest.mark.parametrize("port", ["0", "70000", "taken"])
def test_a_bad_port_is_one_line(tmp_path, port):
    import socket

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        if port == "taken":
            port = str(held.getsockname()[1])
        done = subprocess.run([sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--ticks", "5",
                               "--live", port, "--json", str(tmp_path / "r.json")],
                              capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 2
    assert done.stderr.startswith("error: live: port") and done.stderr.count("\n") == 1, done.stderr
    assert not (tmp_path / "r.json").exists()


def test_the_world_side_feeds_the_server_without_a_mesh():
    """``LiveFeed`` (the world's hooks) and the server process, with the
    reports of a run made up here: every channel reaches a protocol client
    while the ticks come, and the estimates are the reports'."""
    import threading
    from types import SimpleNamespace

    import numpy as np

    from diskf_mesh.data.faults import FaultConfig
    from diskf_mesh.data.scenario import load_scenario, simulate
    from diskf_mesh.live.server import LiveFeed

    scn = load_scenario("quadrants").with_overrides(steps=2000)
    trace = simulate(scn, [0])
    n, m = trace.model.n, trace.model.m
    ids = [a.id for a in scn.agents]
    port = free_port()
    feed = LiveFeed(port, trace, scn, scenario="quadrants", algorithm="diskf", seed=0, run_id="feedtest",
                    faults=FaultConfig())
    stop = threading.Event()

    def ticks():
        for k in range(1, 2001):
            if stop.is_set():
                break
            feed.on_open(k, ids)
            for j, i in enumerate(ids):
                feed.on_report(SimpleNamespace(
                    tick=k, sender=i, x=np.full(n, float(j)), P=np.eye(n) * (j + 1), d=np.zeros(m), d_valid=True,
                    counters={"published": k}, fused=(), not_fused=(), sent_digest=bytes(16), digests=()))
            feed.on_close(k, [])
            time.sleep(0.01)

    feeder = threading.Thread(target=ticks)
    feeder.start()
    try:
        channels, got = watch(port, feed._proc, LIVE_TOPICS, timeout=60)
    finally:
        stop.set()
        feeder.join()
        assert feed.finish("stopped") is None
    assert set(channels) == set(CHANNELS) | {scene.TOPIC}
    for msg in got["/agents/estimates"]:
        for e in msg["estimates"]:
            j = ids.index(e["agent"])
            assert e["x"] == [float(j)] * n and e["P"] == (np.eye(n) * (j + 1)).tolist()
    assert got["/run"][0]["run_id"] == "feedtest"


def test_the_server_offers_only_the_sdk_subprotocol():
    """foxglove-sdk's server has no option for the older ``foxglove.websocket.v1``
    (docs/live.md): a client asking only for it is refused with HTTP 400;
    one asking for both gets ``foxglove.sdk.v1``."""
    from websockets.exceptions import InvalidStatus

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "diskf_mesh.live.server", str(port)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1", SUBPROTOCOL],
                                        open_timeout=5) as ws:
                    assert ws.subprotocol == SUBPROTOCOL
                    assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
                time.sleep(0.2)
        with pytest.raises(InvalidStatus) as refused:
            websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"], open_timeout=5)
        assert refused.value.response.status_code == 400
    finally:
        proc.stdin.close()
        assert proc.wait(timeout=30) == 0
