"""Every exit status of the commands, in one place.

A run (``up``, ``world``, the simulated network) ends with a status
(``diskf_mesh.engine.verify``: the end-of-run replay on the engine) and exits
with the code this table gives it; ``replay RUN.mcap`` and ``replay
--fused`` exit with the code of the status they find.

    0  OK               exact, or as planned (only the injected faults)
    1  FAILED           a process failed (its one line says why)
    2  BAD_INPUT        bad input, or a duplicate process in the run
    3  INCOMPLETE       agent-ticks missing beyond ``--allow-missing``; a
                        run whose world gave up before any report; a
                        recording that is not whole (``replay RUN.mcap``,
                        whatever the tolerances); for
                        an agent process (``STOPPED``): its estimator
                        diverged, it told the world and left, and the run
                        went on without it
    4  TOO_MANY_MISSES  real time: deadline misses beyond ``--max-miss-rate``
    5  DEGRADED         complete, but agent-ticks fused fewer messages than
                        planned (without ``--allow-degraded``)
    6  DIVERGED         a reported estimate the engine does not reproduce;
                        never accepted
    7  RECORDING_FAILED the run's recording could not be written whole (a
                        full disk): its line names the file and the last
                        tick it holds
    8  UNVERIFIABLE     reported agent-ticks the check cannot verify: built
                        on a state the run did not report (a withheld or
                        lost report, then an estimate or a message the
                        engine does not reproduce); never accepted by
                        ``--allow-missing``, only by
                        ``--accept-unverifiable`` (its line gives the count)
"""
from __future__ import annotations

OK = 0
FAILED = 1
BAD_INPUT = 2
INCOMPLETE = 3
TOO_MANY_MISSES = 4
DEGRADED = 5
DIVERGED = 6
RECORDING_FAILED = 7
UNVERIFIABLE = 8
STOPPED = INCOMPLETE  # an agent process that left because its estimator diverged (it told the world)

EXACT_STATUS, AS_PLANNED_STATUS, DEGRADED_STATUS, DIVERGED_STATUS, INCOMPLETE_STATUS, UNVERIFIABLE_STATUS = (
    "exact", "as planned", "degraded", "diverged", "incomplete", "unverifiable")
STATUSES = (EXACT_STATUS, AS_PLANNED_STATUS, DEGRADED_STATUS, DIVERGED_STATUS, INCOMPLETE_STATUS,
            UNVERIFIABLE_STATUS)
STATUS_EXIT = {EXACT_STATUS: OK, AS_PLANNED_STATUS: OK, DEGRADED_STATUS: DEGRADED, DIVERGED_STATUS: DIVERGED,
               INCOMPLETE_STATUS: INCOMPLETE, UNVERIFIABLE_STATUS: UNVERIFIABLE}
