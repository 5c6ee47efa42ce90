"""``diskf-mesh report``: run every experiment and write the markdown report.

Writes DIR/reproduction.md (tables beside the paper's numbers, figures,
the differences and where DISKF is not the best), DIR/figures/*.png and
DIR/results.json (every number, with its provenance). ``--out docs``
regenerates the committed docs/reproduction.md. The studies run in one
process per core (--jobs); a bar on a terminal, else a line per study and
per held-out case on standard error, says how far it is (none with
--quiet). --heldout also runs the held-out suite (section 11: every
estimator on 148 cases, docs/costs.md says how long); without it, section
11 keeps the suite's results of the last --heldout run in DIR and says
when and from which commit they were made.
"""
from __future__ import annotations

from functools import partial

from diskf_mesh.cli.options import positive_int
from diskf_mesh.cli.progress import Progress
from diskf_mesh.cli.study_options import add_study_command, run_study


def report(cfg, out, quiet: bool = False, jobs: int | None = None, with_heldout: bool = False) -> str:
    from diskf_mesh.studies.report import workers, write_report  # matplotlib: only when drawing

    with Progress("report", quiet, unit="study") as shown:
        def progress(i: int, n: int, title: str, seconds: float) -> None:
            shown.total = n
            if i == 0:
                shown.note(title)
            else:
                shown.step(title, seconds)

        md, js, *figs = write_report(cfg, out, progress, jobs=jobs or workers(), with_heldout=with_heldout)
    return f"report -> {md} ({len(figs)} figures, numbers in {js})"


def register(subparsers) -> None:
    add_study_command(subparsers, "report", "run every experiment, write the markdown report", __doc__,
                      "folder for reproduction.md, figures/ and results.json (created)", report)
    p = subparsers.choices["report"]
    p.add_argument("--jobs", type=positive_int, metavar="N",
                   help="processes for the studies (default: one per core this process may use)")
    p.add_argument("--heldout", action="store_true",
                   help="also run the held-out suite (section 11; a few minutes)")
    p.set_defaults(func=lambda args: run_study(args, partial(report, quiet=args.quiet, jobs=args.jobs,
                                                             with_heldout=args.heldout)))
