"""``diskf-mesh figures``: every figure of the report as PNG, PDF or SVG files.

The scenarios (Scenario 2 with its links), 2-D trajectories of every
estimator against the truth, input estimates per node, x and y against
time, error against communication range, the range-120 / all-to-all bars,
the observation-window variants and the isolated-sensor diagnosis.
"""
from __future__ import annotations

from functools import partial

from diskf_mesh.cli.study_options import add_study_command, drawing, out_dir, run_study


FORMATS = ("png", "pdf", "svg")  # as diskf_mesh.studies.figures.FORMATS, which loads matplotlib


def figures(cfg, out, fmt: str = "png") -> str:
    from diskf_mesh.studies.figures import make_figures  # matplotlib: only when drawing

    return f"{len(make_figures(cfg, out, fmt=fmt))} figures -> {out}"


def register(subparsers) -> None:
    add_study_command(subparsers, "figures", "write every figure of the report (PNG, PDF or SVG)", __doc__,
                      "folder for the figures (created)", figures)
    p = subparsers.choices["figures"]
    p.add_argument("--from", dest="recording", metavar="RUN.mcap",
                   help="instead: the figures of one recorded run (trajectories, links, error over time)")
    p.add_argument("--format", choices=FORMATS, default="png", help="the figures' file format (default png)")
    p.set_defaults(func=lambda args: recording_figures(args) if args.recording
                   else run_study(args, partial(figures, fmt=args.format)))


def recording_figures(args) -> int:
    from diskf_mesh.recording.figures import make_recording_figures
    from diskf_mesh.recording.reader import read

    rec = read(args.recording)
    paths = drawing(args.command, lambda: make_recording_figures(rec, out_dir(args.out), fmt=args.format))
    print(f"{len(paths)} figures of {args.recording} -> {args.out}")
    return 0
