"""mesh.process: one OS process of a run, and one tick through the mesh in the order the code runs it.

    transport      Transport: zenoh sessions (the tests have an in-process bus of their own)
    zenoh_config   session settings (TLS, access control, endpoints)
    shell          runs a machine over a Transport on the wall clock (one lock, timers, Woke)
    checker        the world's check as the run goes, in a thread of its own
    stopping       how a mesh process stops on a signal
    runspec        one run's settings as command lines (launcher, compose)


Each process of a run (the world, ``sim.world``; an agent, ``agents.agent``)
is a protocol machine in a shell:

    machine   ``mesh.protocol.world_machine.WorldMachine``,
              ``mesh.protocol.agent_machine.AgentMachine``: the whole protocol, pure
              (``mesh.protocol.events``: events in with the time ``now``, effects
              out; no thread, no transport, no clock read), so the same
              code runs under zenoh and under the simulated network
              (``mesh.simulated.simnet``), where a seed replays a run event for event
    shell     ``mesh.process.shell.Shell``: the transport's callbacks hand each
              sample, token change, query and reply to the machine under
              one lock, on the transport's thread, and carry out its
              effects there (a put, a token, a timer); the main thread
              fires the machine's timers and tells it when the process was
              not running (``Woke``)

One tick k through the mesh (lockstep; real time differs only in who closes
a tick, ``mesh.protocol.clock``):

 1. world      ``WorldMachine._open_tick(k)``: each live agent's
               measurement (``wire.encode_measurement``, on the agent's own
               key, not express) and then the tick (``wire.encode_tick``:
               every position and the live set), published.
 2. agent      the shell reads each sample at the machine's edge
               (``AgentMachine.read`` -> ``mesh.protocol.intake``): the key
               parsed once (``Keys.parse``: kind and agent id), the payload
               decoded once (``wire.decode_measurement``,
               ``wire.decode_tick``) into a typed event;
               ``AgentMachine._on_meas``, ``_on_tick`` take it if it fits
               the run (``_meas_problem``, ``_tick_problem``). The tick gives the agents linked at k
               (live, in range: ``linked``) and lets through the neighbours'
               messages of k that came before it (``Receiver.release``).
 3. agent      ``AgentMachine._open(k)``: the local step
               (``AgentEstimator.local``), its one message encoded
               (``wire.encode``: the fields its estimator exchanges,
               ``Estimator.exchanged``) and published on a key addressed to
               the linked agents; the collect timer set.
 4. neighbour  at the edge, ``Guard.read`` decodes the payload once
               (``wire.decode``: schema, finite, positive definite) and
               checks the same floats once (magnitude, conditioning,
               information: ``guard``) into a ``MessageArrived``;
               ``AgentMachine._on_msg`` -> ``Receiver.on_message``:
               ``Guard.judge`` checks the tick window; the range gate drops a sender not linked at the
               message's tick; the link's faults (``FaultModel.plan``,
               delayed copies in the ``DelayLine`` until the machine's
               "delay" timer); the message then waits in one place, the
               ``Inbox``, until its tick is fused (one whose tick the world
               has not opened at this agent yet waits for that, before its
               link: ``Receiver.release``).
 5. neighbour  ``AgentMachine._close(k)`` once every linked sender is
               accounted for (arrived, lost, rejected) or the collection
               ends: ``Receiver.take`` -> ``AgentEstimator.fuse`` ->
               ``wire.encode_report`` (the fused estimate, the counters, what
               was fused and why the rest was not, the digests of the fused
               messages) on its report key.
 6. world      ``WorldMachine._on_report`` (``wire.decode_report``) ->
               ``_take`` records it; the last report of tick k closes it
               (``_advance`` -> ``_close_tick``) and opens tick k + 1
               (``_open_tick``, step 1) in the same event.

May import: core, estimators, data, engine, mesh.wire, mesh.security, mesh.protocol.
"""
