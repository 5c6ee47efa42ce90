"""``diskf-mesh report``: run every experiment and write the markdown report.

Writes DIR/reproduction.md (tables beside the paper's numbers, figures,
the differences and where DISKF is not the best), DIR/figures/*.png and
DIR/results.json (every number, with its provenance). ``--out docs``
regenerates the committed docs/reproduction.md. The studies run in one
process per core (--jobs); one line per study on standard error says how
far it is (none with --quiet). --heldout also runs the held-out suite
(section 11: every estimator on 148 cases, a few minutes); without it,
section 11 keeps the suite's results of the last --heldout run in DIR and
says when and from which commit they were made.
"""
from __future__ import annotations

import sys
from functools import partial

from diskf_mesh.cli.options import positive_int
from diskf_mesh.cli.study_options import add_study_command, run_study


def progress_line(i: int, n: int, title: str, seconds: float) -> None:
    print(f"report: [{i}/{n}] {title}: {seconds:.1f} s", file=sys.stderr, flush=True)


def report(cfg, out, lines: bool = True, jobs: int | None = None, with_heldout: bool = False) -> str:
    from diskf_mesh.studies.report import workers, write_report  # matplotlib: only when drawing

    md, js, *figs = write_report(cfg, out, progress_line if lines else None, jobs=jobs or workers(),
                                 with_heldout=with_heldout)
    return f"report -> {md} ({len(figs)} figures, numbers in {js})"


def register(subparsers) -> None:
    add_study_command(subparsers, "report", "run every experiment, write the markdown report", __doc__,
                      "folder for reproduction.md, figures/ and results.json (created)", report)
    p = subparsers.choices["report"]
    p.add_argument("--jobs", type=positive_int, metavar="N",
                   help="processes for the studies (default: one per core this process may use)")
    p.add_argument("--heldout", action="store_true",
                   help="also run the held-out suite (section 11; a few minutes)")
    p.set_defaults(func=lambda args: run_study(args, partial(report, lines=not args.quiet, jobs=args.jobs,
                                                             with_heldout=args.heldout)))
