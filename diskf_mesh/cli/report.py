"""``diskf-mesh report``: run every experiment and write the markdown report.

Writes DIR/reproduction.md (tables beside the paper's numbers, figures,
the differences and where DISKF is not the best), DIR/figures/*.png and
DIR/results.json (every number). ``--out docs`` regenerates the committed
docs/reproduction.md.
"""
from __future__ import annotations

from diskf_mesh.cli.study_options import add_study_command


def report(cfg, out) -> str:
    from diskf_mesh.studies.report import write_report  # matplotlib: only when drawing

    md, js, *figs = write_report(cfg, out)
    return f"report -> {md} ({len(figs)} figures, numbers in {js})"


def register(subparsers) -> None:
    add_study_command(subparsers, "report", "run every experiment, write the markdown report", __doc__,
                      "folder for reproduction.md, figures/ and results.json (created)", report)
