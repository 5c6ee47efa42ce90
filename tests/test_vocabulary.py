"""One vocabulary across the commands: ``--ticks`` (``--steps`` the old
spelling, with a note), ``--estimator`` and ``--estimators`` in either
spelling, the nearest match for every unknown option or command, nothing
written by a command that fails before it starts, and the API's surface
(read-only result arrays, ``dir``, docstrings)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import diskf_mesh
from cli_helpers import run_cli
from diskf_mesh import estimators
from diskf_mesh.cli.main import COMMAND_MODULES, build_parser

ROOT = Path(__file__).resolve().parents[1]
QUICK = ["--scenario", "dynamic", "--seeds", "1", "--quiet"]


def _parse(argv):
    return build_parser(COMMAND_MODULES).parse_args(argv)


@pytest.mark.parametrize("command", ["experiment", "simulate", "report", "figures", "up", "world"])
def test_every_command_takes_ticks_and_the_old_spelling_with_a_note(command, capsys):
    extra = ["--out", "x"] if command in ("simulate", "report", "figures") else []
    assert _parse([command, "--ticks", "7", *extra]).ticks == 7
    assert capsys.readouterr().err == ""
    assert _parse([command, "--steps", "7", *extra]).ticks == 7
    assert capsys.readouterr().err == "note: --steps is now --ticks\n"
    (sub,) = [a for a in build_parser(COMMAND_MODULES)._actions if a.__class__.__name__ == "_SubParsersAction"]
    shown = sub.choices[command].format_help()
    assert "--ticks K" in shown and "--steps" not in shown  # the old spelling works, --help teaches the new


def test_the_old_spelling_gives_the_same_result(tmp_path, capsys):
    docs = []
    for flag in ("--ticks", "--steps"):
        out = tmp_path / f"{flag[2:]}.json"
        code, _, err = run_cli(["experiment", *QUICK, flag, "12", "--estimators", "diskf", "--json", out], capsys)
        assert code == 0, err
        docs.append({k: v for k, v in json.loads(out.read_text()).items() if k != "provenance"})
    assert docs[0] == docs[1] and docs[0]["diskf"]


@pytest.mark.parametrize("argv, dest, value", [
    (["experiment", "--estimator", "diskf"], "estimators", ["diskf"]),
    (["experiment", "--estimators", "diskf,kcf"], "estimators", ["diskf", "kcf"]),
    (["up", "--estimators", "kcf"], "algorithm", "kcf"),
    (["up", "--estimator", "kcf"], "algorithm", "kcf"),
    (["world", "--estimators", "kcf"], "algorithm", "kcf"),
])
def test_estimator_and_estimators_are_one_word(argv, dest, value):
    assert getattr(_parse(argv), dest) == value


def test_a_command_of_one_estimator_says_so_for_a_list(capsys):
    code, _, err = run_cli(["up", "--estimators", "diskf,kcf"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "one estimator here" in err, err


@pytest.mark.parametrize("argv, said", [
    (["experiment", "--tiks", "5"], "error: unknown option --tiks (did you mean --ticks?)"),
    (["up", "--estimatr", "kcf"], "error: unknown option --estimatr (did you mean --estimator?)"),
    (["report", "--outt", "x"], "error: unknown option --outt (did you mean --out?)"),
    (["report", "--sedes", "2"], "error: unknown option --sedes (did you mean --seeds?)"),  # before "--out is required"
    (["replay", "--outt", "e.json"], "error: unknown option --outt (did you mean --out?)"),
    (["simulate", "--seeds", "3", "--out", "t.json"], "error: unknown option --seeds (did you mean --seed?)"),
    (["inspect", "--jsn", "x"], "error: unknown option --jsn (did you mean --json?)"),
    (["experimnt"], "error: unknown command experimnt (did you mean experiment?)"),
])
def test_an_unknown_option_or_command_gets_its_nearest_match(argv, said, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(argv, capsys)
    assert (code, out, err) == (2, "", said + "\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [["up", "--scenario", "nosuch"], ["up", "--live", "99999"],
                                  ["up", "--scenario", "nosuch", "--logs", "logs/run"],
                                  ["up", "--network", "simulated", "--scenario", "nosuch"],
                                  ["experiment", "--scenario", "nosuch", "--json", "r.json"]])
def test_nothing_is_written_when_a_command_fails_before_it_starts(argv, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli(argv, capsys)
    assert code == 2 and err.startswith("error: "), err
    assert list(tmp_path.iterdir()) == []


def test_result_arrays_are_read_only():
    run = diskf_mesh.run("quadrants", "diskf", seeds=[0], steps=5)
    for name in ("x", "P", "d", "d_valid"):
        arr = getattr(run, name)
        assert not arr.flags.writeable, name
        with pytest.raises(ValueError):
            arr[...] = 0
    assert run.to_dict()["format"] == "diskf-estimates/1"
    assert np.isfinite(run.x).all()


def test_the_package_shows_its_api_only():
    shown = dir(diskf_mesh)
    assert not {"API", "TYPE_CHECKING", "annotations"} & set(shown)
    assert {"run", "experiment", "Run", "InputError", "__version__"} <= set(shown)


@pytest.mark.parametrize("name", estimators.NAMES)
def test_every_estimator_class_has_a_docstring(name):
    cls = estimators.get(name)
    assert "__doc__" in vars(cls) and len(cls.__doc__.split()) > 5, cls


def test_a_table_of_one_estimator_marks_no_best(capsys):
    code, out, _ = run_cli(["experiment", *QUICK, "--ticks", "5", "--estimators", "diskf"], capsys)
    assert code == 0 and "*" not in out
    code, out, _ = run_cli(["experiment", *QUICK, "--ticks", "5", "--estimators", "diskf,kcf"], capsys)
    assert code == 0 and "*" in out


def test_the_readme_holds_no_notes_to_its_writers():
    assert "<!--" not in (ROOT / "README.md").read_text()
