"""The zenoh transport's callbacks, in one process: two sessions on loopback."""
from __future__ import annotations

import _thread
import queue
import socket
import threading
import time

from diskf_mesh.mesh.process.transport import ZenohTransport
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions

KEY = "diskf-test/transport/keep"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_each_zenoh_thread_keeps_its_python_thread_state_from_sample_to_sample():
    """Zenoh calls Python from threads of its own: a sample's callback runs
    in the thread state its thread's first callback had (a thread-local set
    there is there for the next sample), not in a new one per sample."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    local = _thread._local()  # a thread-local lives in its thread state
    seen = queue.Queue()

    def on_sample(key, payload):
        seen.put((threading.get_ident(), getattr(local, "mark", False)))
        local.mark = True

    listener = ZenohOptions(listen=(endpoint,), no_multicast_scouting=True, insecure=True)
    dialer = ZenohOptions(connect=(endpoint,), no_multicast_scouting=True, insecure=True)
    with ZenohTransport(listener) as sub, ZenohTransport(dialer) as pub:
        sub.subscribe(KEY, on_sample)
        stop = time.monotonic() + 10.0
        while seen.empty() and time.monotonic() < stop:  # until the subscription has reached the publisher
            pub.put(KEY, b"first")
            time.sleep(0.05)
        for _ in range(50):
            pub.put(KEY, b"next")
            time.sleep(0.002)
        time.sleep(0.5)
    samples = []
    while not seen.empty():
        samples.append(seen.get())
    threads = {ident for ident, _ in samples}
    fresh = [ident for ident, kept in samples if not kept]
    assert len(samples) >= 50
    assert sorted(fresh) == sorted(threads)  # a new thread state only on a thread's first sample
