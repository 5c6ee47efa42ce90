"""The shell that runs a protocol machine over a transport on the real clock."""
from __future__ import annotations

import threading
import time

import pytest

from diskf_mesh.mesh.protocol.events import (Answer, Ask, AskTokens, DeclareQueryable, DeclareToken, Finish, Interrupt,
                                    Publish, Query, Reply, Sample, SetTimer, Subscribe, Timer, Tokens, Woke)
from diskf_mesh.mesh.process.shell import Shell
from local_bus import LocalBus


class Scripted:
    """A machine that answers each event with ``script(event, now)`` and
    keeps every event it was handed."""

    read = Sample  # takes its samples as they are

    def __init__(self, first, script):
        self.first, self.script, self.seen = first, script, []

    def start(self, now):
        return self.first(now)

    def handle(self, event, now):
        self.seen.append(event)
        return self.script(event, now)


def test_a_timer_fires_when_due_and_finish_ends_the_run():
    t0 = []
    m = Scripted(lambda now: t0.append(now) or [SetTimer("a", now + 0.05), SetTimer("b", now + 0.02)],
                 lambda e, now: [Finish("done", 0)] if e == Timer("a") else [])
    assert Shell(m, LocalBus().transport()).run() == Finish("done", 0)
    assert m.seen == [Timer("b"), Timer("a")]


def test_a_late_wake_up_is_a_woke_event():
    """The clock jumps 5 s while the main thread sleeps (as a SIGSTOP would
    make it): the machine hears Woke with that lateness."""
    offset = [0.0]
    clock = lambda: time.monotonic() + offset[0]  # noqa: E731
    m = Scripted(lambda now: [SetTimer("t", now + 0.3)],
                 lambda e, now: [Finish("done", 0)] if isinstance(e, Timer) else [])
    threading.Timer(0.1, lambda: offset.__setitem__(0, 5.0)).start()
    Shell(m, LocalBus().transport(), clock=clock).run()
    woke = [e for e in m.seen if isinstance(e, Woke)]
    assert len(woke) == 1 and 4.5 < woke[0].late < 5.5 and m.seen[-1] == Timer("t")


def test_samples_tokens_queries_and_liveliness_queries_round_trip():
    bus = LocalBus()
    answering = Scripted(lambda now: [DeclareQueryable("q/*"), Subscribe("s/**")],
                         lambda e, now: ([Answer(e.qid, e.payload + b"!")] if isinstance(e, Query) else
                                         [Finish("done", 0)] if isinstance(e, Sample) else []))
    a = Shell(answering, bus.transport())
    done = threading.Thread(target=a.run, daemon=True)
    done.start()
    time.sleep(0.1)

    def asking_script(e, now):
        if isinstance(e, Tokens):
            return [Ask(7, "q/1", b"hi", 2.0)]
        if isinstance(e, Reply):
            return [Publish("s/x", e.payload), Finish("asked", 0)]
        return []

    asking = Scripted(lambda now: [DeclareToken("tok/1"), AskTokens(1, "tok/*", 0.5)], asking_script)
    assert Shell(asking, bus.transport()).run() == Finish("asked", 0)
    done.join(5)
    assert asking.seen == [Tokens(1, ("tok/1",)), Reply(7, b"hi!")]
    assert [type(e) for e in answering.seen] == [Query, Sample] and answering.seen[1].payload == b"hi!"


def test_a_query_nobody_answers_replies_none():
    m = Scripted(lambda now: [Ask(1, "nobody/here", b"", 0.1)], lambda e, now: [Finish("done", 0)])
    Shell(m, LocalBus().transport()).run()
    assert m.seen == [Reply(1, None)]


def test_interrupt_reaches_the_machine():
    m = Scripted(lambda now: [], lambda e, now: [Finish("stopped", 0, e.why)] if isinstance(e, Interrupt) else [])
    shell = Shell(m, LocalBus().transport())
    threading.Timer(0.05, shell.interrupt, args=("SIGTERM",)).start()
    assert shell.run() == Finish("stopped", 0, "SIGTERM")


def test_a_callbacks_failure_is_raised_by_run():
    bus = LocalBus()

    def script(e, now):
        raise ValueError("broken")

    m = Scripted(lambda now: [Subscribe("s")], script)
    shell = Shell(m, bus.transport())
    threading.Timer(0.05, bus.transport().put, args=("s", b"x")).start()
    with pytest.raises(ValueError, match="broken"):
        shell.run()


def test_unanswered_queries_held_are_bounded(monkeypatch):
    import diskf_mesh.mesh.process.shell as shell_module

    monkeypatch.setattr(shell_module, "QUERIES_HELD", 3)
    m = Scripted(lambda now: [], lambda e, now: [])
    shell = Shell(m, LocalBus().transport())
    for n in range(10):
        shell._on_query("q/1", b"", lambda p: None)
    assert list(shell._queries) == [8, 9, 10]
