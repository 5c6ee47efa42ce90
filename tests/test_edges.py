"""The command line's edges: Ctrl-C and SIGTERM at any moment end with one
line and no traceback; an unknown option, a mistyped scenario name, a folder
given as a scenario and a broken file each get one line that says what is
wrong and where; --help is plain text and lists every exit status; figures
come in PNG, PDF or SVG, with the truth in a colour no estimator has."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest

from cli_helpers import run_cli
from diskf_mesh.cli import help_text
from diskf_mesh.cli.main import COMMAND_MODULES, build_parser

CLI = [sys.executable, "-m", "diskf_mesh.cli.main"]
LONG = ["experiment", "--scenario", "random-geometric", "--agents", "200", "--seeds", "10", "--ticks", "1000", "--quiet"]


def started(argv, tmp_path):
    return subprocess.Popen([*CLI, *argv], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop(proc, sig, after: float) -> tuple[int, str]:
    time.sleep(after)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err


def main_running(proc, timeout: float = 60.0) -> None:
    """Wait until ``proc`` runs the command line's ``main`` (it catches
    SIGTERM from then on: /proc's SigCgt). A signal before that reaches the
    interpreter's own start, which prints Python's traceback for any program."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            status = open(f"/proc/{proc.pid}/status").read()
        except FileNotFoundError:
            return
        caught = int(re.search(r"^SigCgt:\s*([0-9a-f]+)", status, re.M).group(1), 16)
        if caught & (1 << (signal.SIGTERM - 1)):
            return
        time.sleep(0.005)
    raise AssertionError("the command did not start")


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux /proc")
@pytest.mark.parametrize("later", [0.0, 0.3, 2.0])
def test_ctrl_c_at_any_moment_is_one_line(tmp_path, later):
    proc = started(LONG, tmp_path)
    main_running(proc)
    code, err = stop(proc, signal.SIGINT, later)
    assert code == 130 and "Traceback" not in err
    assert err.strip() == "interrupted", err


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux /proc")
@pytest.mark.parametrize("later", [0.0, 0.3, 2.0])
def test_sigterm_is_one_line(tmp_path, later):
    proc = started(LONG + ["--json", "r.json"], tmp_path)
    main_running(proc)
    code, err = stop(proc, signal.SIGTERM, later)
    assert code == 143 and err.strip() == "terminated", err
    assert not list(tmp_path.iterdir())  # no partial output and no temporary file


@pytest.mark.mesh
@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_up_stopped_early_says_so_in_a_line(tmp_path, sig, code, word):
    proc = started(["up", "--ticks", "5000", "--json", "r.json", "--quiet"], tmp_path)
    got, err = stop(proc, sig, 0.3)
    assert got == code and "Traceback" not in err and word in err, err
    assert len(err.strip().splitlines()) <= 2, err


@pytest.mark.parametrize("argv, words", [
    (["--versoin"], ["unknown option --versoin", "did you mean --version?"]),
    (["experiment", "--seds", "3"], ["unknown option --seds", "did you mean --seeds?"]),
    (["experiment", "--scenario", "dynamc"], ["unknown scenario 'dynamc'", "did you mean 'dynamic'?"]),
])
def test_a_typo_gets_one_line_with_a_suggestion(argv, words, capsys):
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, err
    assert err.startswith("error: ") and all(w in err for w in words), err


def test_an_option_of_another_command_is_not_suggested_as_itself(capsys):
    """``experiment --network``: ``--network`` is ``up``'s."""
    code, out, err = run_cli(["experiment", "--network", "peers"], capsys)
    assert code == 2 and err.strip() == "error: unknown option --network", err


@pytest.mark.parametrize("argv", [["world", "--startup-timeout", "-5"], ["up", "--collect-timeout", "0"],
                                  ["agent", "--world-timeout", "nan"], ["host", "--startup-timeout", "inf"]])
def test_a_timeout_must_be_a_positive_number(argv, capsys):
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"error: argument {argv[1]}: must be a number of seconds above 0"), err


def test_a_folder_given_as_a_scenario_says_so(tmp_path, capsys):
    code, _, err = run_cli(["experiment", "--scenario", tmp_path], capsys)
    assert code == 2 and f"{tmp_path} is a folder" in err and len(err.strip().splitlines()) == 1


def test_a_broken_file_is_named(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "diskf-trace/1"}')
    code, _, err = run_cli(["replay", bad, "--out", tmp_path / "e.json"], capsys)
    assert code == 2 and err.startswith("error: ") and str(bad) in err and len(err.strip().splitlines()) == 1
    bad.write_text("{")
    code, _, err = run_cli(["replay", bad, "--out", tmp_path / "e.json"], capsys)
    assert code == 2 and str(bad) in err


def _helps():
    parser = build_parser(COMMAND_MODULES)
    (sub,) = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
    return {"diskf-mesh": parser.format_help(), **{name: p.format_help() for name, p in sub.choices.items()}}


def test_help_is_plain_text_and_lists_every_exit_status():
    from diskf_mesh.core import exits

    codes = {v for k, v in vars(exits).items() if k.isupper() and isinstance(v, int) and not isinstance(v, bool)}
    assert codes <= {code for code, _ in help_text.EXIT_STATUSES}
    helps = _helps()
    assert {"up", "world", "agent", "experiment", "replay", "report", "figures"} <= set(helps)
    internal = re.compile(r"``|\b(diskf_mesh|sim|agents)\.\w|\b[A-Z][A-Z0-9]*_[A-Z0-9_]+\b|\bpython -m\b")
    for name, text in helps.items():
        words = re.sub(r"-[\w-]+[ =]\[?[A-Z][A-Z0-9_]*", "", text)  # an option's metavar (--run-id RUN_ID) is no name
        assert not internal.search(words), (name, internal.search(words).group(0))
        statuses = text.split("exit status:", 1)[1]
        for code, _ in help_text.EXIT_STATUSES:
            assert re.search(rf"^\s+{code}\s", statuses, re.M), (name, code)


def test_plain_text_keeps_what_a_user_needs():
    doc = ("Starts the world (``python -m sim.world``) and ``PEERS_UP_TO`` peers "
           "(``diskf_mesh.mesh.security.credentials``); see ``--logs`` and docs/hosts.md.")
    text = help_text.plain(doc)
    assert text == "Starts the world (diskf-mesh world) and 16 peers; see --logs and docs/hosts.md." or \
        ("diskf-mesh world" in text and "--logs" in text and "``" not in text and "credentials" not in text)


@pytest.mark.parametrize("fmt, magic", [("png", b"\x89PNG"), ("pdf", b"%PDF"), ("svg", b"<?xml")])
def test_figures_in_every_format(tmp_path, capsys, fmt, magic):
    out = tmp_path / "figs"
    code, stdout, err = run_cli(["figures", "--out", out, "--seeds", "1", "--ticks", "20", "--quiet",
                                 "--format", fmt], capsys)
    assert code == 0, err
    files = sorted(out.iterdir())
    assert len(files) == 13 and all(p.suffix == f".{fmt}" and p.read_bytes()[:len(magic)] == magic for p in files)


def test_the_truth_has_a_colour_no_estimator_has():
    from matplotlib.colors import to_rgb

    from diskf_mesh.studies import figures

    truth = to_rgb(figures.TRUTH_COLOR)
    for name, colour in figures.COLORS.items():
        distance = sum((a - b) ** 2 for a, b in zip(truth, to_rgb(colour))) ** 0.5
        assert distance > 0.3, (name, colour)


def test_the_truth_is_drawn_in_its_colour(tmp_path):
    from matplotlib.colors import to_rgb

    from diskf_mesh.studies import figures
    from diskf_mesh.studies import suite as studies

    cfg = studies.StudyConfig(seeds=1, steps=20, quiet=True)
    run = figures.Run.of(cfg, studies.STATIONARY, studies.RING, "ring")
    drawn = []
    real = figures._save

    def keep(fig, path):
        drawn.extend(line for ax in fig.axes for line in ax.get_lines() if line.get_label() == "truth")
        return real(fig, path)

    figures._save = keep
    try:
        figures.plot_trajectories(run, tmp_path / "t.png")
    finally:
        figures._save = real
    assert drawn and all(to_rgb(line.get_color()) == to_rgb(figures.TRUTH_COLOR) for line in drawn)


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux")
def test_report_shows_a_line_per_study_when_not_a_terminal(tmp_path):
    done = subprocess.run([*CLI, "report", "--out", str(tmp_path), "--seeds", "1", "--ticks", "15", "--jobs", "2"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.startswith("report: [")]
    from diskf_mesh.studies import report

    assert len(lines) == len(report.JOBS) + 1 and lines[-1].startswith(f"report: [{len(lines)}/{len(lines)}]")
    assert any("figures" in line for line in lines)


@pytest.mark.mesh
def test_up_without_logs_leaves_no_folder_when_it_succeeds(tmp_path):
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    done = subprocess.run([*CLI, "up", "--ticks", "3", "--json", str(tmp_path / "r.json"), "--quiet"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr
    assert not list(tmp_path.glob("diskf-up-*")) and "logs:" not in done.stdout
    bad = subprocess.run([*CLI, "up", "--ticks", "3", "--json", str(tmp_path / "r.json"), "--quiet",
                          "--startup-timeout", "0.01"], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=240)
    kept = list(tmp_path.glob("diskf-up-*"))
    assert bad.returncode != 0 and len(kept) == 1 and str(kept[0]) in bad.stdout + bad.stderr, bad.stderr


@pytest.mark.mesh
def test_an_interrupted_recording_attaches_only_the_ticks_it_ran(tmp_path):
    import json

    from mcap.records import Attachment

    from diskf_mesh.recording import layout, reader

    path = tmp_path / "run.mcap"
    proc = started(["up", "--ticks", "3000", "--record", str(path), "--json", "r.json", "--quiet"], tmp_path)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 180:
        time.sleep(0.5)
        try:
            if reader.read(path).ticks >= 5:
                break
        except Exception:  # not even the first tick yet
            continue
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=120)
    rec = reader.read(path)
    attached = sum(len(json.loads(r.data)["y"]) for r in reader.scan(path.read_bytes())
                   if isinstance(r, Attachment))
    assert 5 <= rec.ticks < 3000 and rec.planned_ticks == 3000
    assert rec.ticks <= attached < rec.ticks + layout.SEGMENT_TICKS
    assert reader.read(path).trace.shape[1] == attached
