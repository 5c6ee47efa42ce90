"""``diskf-mesh resilience``: what insiders' lies do to the honest agents of
the default estimator: without the screen before fusion, with it alone (the
engine), and with it and the world's check as the run goes (the world names
a liar and quarantines it, as in ``up``: the engine on the live sets the
world announces, the simulated network's run bit for bit).

Scenario 2 and a 25-agent random geometric network (one and two insiders: its best-connected agents),
each lie of docs/security.md's table (offsets 10 to 5,000 m, drifts, a
shrunk covariance, a replayed stale estimate, a false input) from tick 50,
over seeds 0..S-1. Writes the table into DIR/security.md between its
markers (else DIR/resilience.md), the figure DIR/figures/resilience.png and
the numbers DIR/resilience.json. ``--out docs`` regenerates the committed
table.
"""
from __future__ import annotations

from diskf_mesh.cli.study_options import add_study_command


def resilience(cfg, out) -> str:
    from diskf_mesh.cli.progress import Progress
    from diskf_mesh.studies import resilience as study

    command = f"diskf-mesh resilience --out {out} --seeds {cfg.seeds}" + (f" --ticks {cfg.steps}" if cfg.steps else "")
    with Progress("resilience", quiet=cfg.quiet and not cfg.lines, total=len(study.SETTINGS) * len(study.LIES),
                  unit="cell") as progress:
        rows = study.measure(range(cfg.seeds), cfg.steps, progress=lambda n: progress.step(n=n))
    table, fig, numbers = study.write(rows, out, command)
    missed = study.missing(rows)
    return (f"resilience -> {table}, {fig}, {numbers}: {len(rows) - len(missed)} of {len(rows)} cells within "
            f"{study.TARGET}x the clean run's honest MAE with the screen and the world's check")


def register(subparsers) -> None:
    add_study_command(subparsers, "resilience", "honest error under insiders' lies, with and without the screen",
                      __doc__, "folder for security.md's table (or resilience.md), figures/ and resilience.json",
                      resilience)
