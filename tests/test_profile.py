"""``Phases``: where a mesh process's time goes (``--profile``)."""
from __future__ import annotations

import threading

from diskf_mesh.mesh.protocol.profile import WORLD_PHASES, Phases


class Clock:
    """A clock the test moves by hand, per thread for the CPU."""

    def __init__(self):
        self.now = 0.0
        self.local = threading.local()

    def wall(self):
        return self.now

    def cpu(self):
        return getattr(self.local, "cpu", 0.0)

    def spend(self, seconds):  # this thread works: wall and its own CPU move together
        self.now += seconds
        self.local.cpu = self.cpu() + seconds


def test_a_span_beside_the_process_counts_its_cpu_and_no_wall():
    """The world decodes from 0 to 2 s; the check's thread replays from 2 to
    5 s beside it, 3 s of its own CPU; the world waits for it from 2 to 3 s,
    then nothing runs in the world until 6 s. The wall column adds up to the
    6 s that passed (the replay overlaps the world's waiting), the check's
    CPU is the thread's 3 s, and the world's waiting for it is its own
    phase."""
    clock = Clock()
    prof = Phases(WORLD_PHASES, "world", wall=clock.wall, cpu=clock.cpu, process_cpu=clock.cpu)
    prof.waiting = "wait-reports"
    began, go_on = threading.Event(), threading.Event()

    def replay():
        prof.begin(beside=True)
        began.set()
        go_on.wait()
        clock.local.cpu = 3.0
        prof.end("check")

    prof.begin()
    clock.spend(2.0)
    prof.end("decode")
    thread = threading.Thread(target=replay)
    thread.start()
    began.wait()
    prof.begin()
    clock.now = 3.0  # blocked on the thread: wall, no CPU of the world's
    prof.end("wait-check")
    clock.now = 5.0
    go_on.set()
    thread.join()
    clock.now = 6.0
    prof.stop()
    assert prof.wall == {**dict.fromkeys(WORLD_PHASES, 0.0), "decode": 2.0, "wait-check": 1.0, "wait-reports": 3.0}
    assert prof.cpu == {**dict.fromkeys(WORLD_PHASES, 0.0), "decode": 2.0, "check": 3.0}
    assert sum(prof.wall.values()) == prof.summary()["elapsed_s"] == 6.0
