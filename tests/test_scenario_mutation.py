"""Mutated shipped scenarios end cleanly: an ``InputError`` (the CLI's one
``error:`` line and exit 2) or a successful run, never a traceback.

Hypothesis mutates the parsed TOML of every shipped scenario (replace a
value by one of another type or range, delete a key, add or misspell a
key), writes it back as TOML, loads it the way the CLI does and runs a
short engine experiment on what loads, with the table printed. A few cases
run the real command line in a subprocess.
"""
from __future__ import annotations

import copy
import json
import math
import os
import re
import subprocess
import sys
import tomllib
import warnings
from importlib import resources

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diskf_mesh import estimators as algorithms
from diskf_mesh.core.errors import InputError
from diskf_mesh.studies.experiment import format_table, run_experiment, settings_for
from diskf_mesh.data.scenario import parse_scenario, shipped_scenarios

SHIPPED = {name: tomllib.loads((resources.files("diskf_mesh") / "scenarios" / f"{name}.toml").read_text())
           for name in shipped_scenarios()}
STEPS = 3  # ticks of the short run


# --------------------------------------------------------------------------
# a small TOML writer for the documents above (tables, arrays of tables,
# inline values)
# --------------------------------------------------------------------------
def _string(v: str) -> str:
    """A TOML basic string (JSON's escapes, and DEL, which TOML refuses raw and JSON leaves as it is)."""
    return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")


def _key(k) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _string(k)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def to_toml(doc: dict) -> str:
    lines = [f"{_key(k)} = {_value(v)}" for k, v in doc.items() if not isinstance(v, dict) and not _is_table_array(v)]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"[{_key(k)}]")
            lines += [f"{_key(kk)} = {_value(vv)}" for kk, vv in v.items()]
        elif _is_table_array(v):
            for item in v:
                lines.append(f"[[{_key(k)}]]")
                lines += [f"{_key(kk)} = {_value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


def test_writer_round_trips_the_shipped_scenarios():
    for doc in SHIPPED.values():
        assert tomllib.loads(to_toml(doc)) == doc


# --------------------------------------------------------------------------
# mutations
# --------------------------------------------------------------------------
def paths(node, prefix=()):
    """Every key path into a document: tables, list items and leaves."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += paths(v, prefix + (i,))
    return out


INTS = st.one_of(st.sampled_from([-1, 0, 1, 2, 3, 7, 2**31, 2**63 - 1, 2**63, 2**64, -2**63, 10**6]),
                 st.integers(-5, 300))
FLOATS = st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, -1.0, 1e-300, 1e300, 1e154, 0.5]),
                   st.floats(allow_nan=True, allow_infinity=True))
SCALARS = st.one_of(INTS, FLOATS, st.booleans(), st.text(max_size=8),
                    st.sampled_from(["none", "range", "all", "quadrant", "always", "matrix", "rotation", "step",
                                     "constant", "random-geometric", "bounded"]))
VALUES = st.one_of(
    SCALARS,
    st.lists(st.one_of(INTS, FLOATS), max_size=3),
    st.lists(st.lists(st.one_of(INTS, FLOATS), min_size=0, max_size=3), max_size=3),
    st.sampled_from(["[]", "{}", "[[]]", "[{}]"]).map(json.loads),  # fresh objects: a case may grow them
    st.dictionaries(st.sampled_from(["id", "H", "R", "kind", "x"]), SCALARS, max_size=2),
)


def typo(key: str, i: int) -> str:
    """A misspelling of ``key``: a letter dropped, doubled or swapped."""
    if len(key) < 2:
        return key + "x"
    j = i % (len(key) - 1)
    return [key[:j] + key[j + 1:], key[:j] + key[j] + key[j:], key[:j] + key[j + 1] + key[j] + key[j + 2:]][i % 3]


def _parent(doc, path):
    node = doc
    for k in path[:-1]:
        node = node[k]
    return node


@st.composite
def nearby(draw, value):
    """A value of the same type as ``value``, often still valid."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        factor = draw(st.sampled_from([0, -1, 0.5, 2, 1e-3, 1e3, 1e9]))
        out = value * factor
        return int(out) if isinstance(value, int) and draw(st.booleans()) else float(out)
    if isinstance(value, str):
        return draw(st.sampled_from(["none", "range", "all", "ring", "quadrant", "always", "matrix", "rotation",
                                     "step", "constant", "paper", value.upper(), value + " "]))
    if isinstance(value, list) and value:
        out = copy.deepcopy(value)
        i = draw(st.integers(0, len(out) - 1))
        choice = draw(st.sampled_from(["item", "drop", "repeat"]))
        if choice == "item":
            out[i] = draw(nearby(out[i]))
        elif choice == "drop":
            del out[i]
        else:
            out.append(copy.deepcopy(out[i]))
        return out
    return draw(VALUES)


@st.composite
def mutated(draw):
    name = draw(st.sampled_from(sorted(SHIPPED)))
    doc = copy.deepcopy(SHIPPED[name])
    for _ in range(draw(st.integers(1, 2))):
        every = paths(doc)
        if not every:
            break
        path = draw(st.sampled_from(every))
        parent, last = _parent(doc, path), path[-1]
        op = draw(st.sampled_from(["nearby", "nearby", "nearby", "replace", "replace", "delete", "add", "misspell"]))
        if op == "nearby":
            parent[last] = draw(nearby(parent[last]))
        elif op == "replace":
            parent[last] = draw(VALUES)
        elif op == "delete":
            del parent[last]
        elif isinstance(parent, dict) and op == "add":
            parent[draw(st.sampled_from(["omega", "range", "period", "phase", "agents", "id", "extra", "A"]))] = \
                draw(VALUES)
        elif isinstance(parent, dict) and op == "misspell" and isinstance(last, str):
            parent[typo(last, draw(st.integers(0, 30)))] = parent.pop(last)
        elif isinstance(parent, list):
            parent.append(copy.deepcopy(parent[last]))  # a repeated item (an agent twice, a longer row)
    return name, doc


def load_and_run(doc: dict, algorithm: str) -> str:
    """What the CLI does with a scenario file (``load_scenario``: TOML text,
    then ``parse_scenario``), in-process, for STEPS ticks."""
    scn = parse_scenario(tomllib.loads(to_toml(doc)))
    setting, = settings_for([scn.topology])
    results = run_experiment(scn, [setting], [algorithm], [0], steps=STEPS)
    return format_table(results)


@settings(max_examples=1000, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(case=mutated(), algorithm=st.sampled_from(algorithms.NAMES))
def test_mutated_scenarios_fail_cleanly_or_run(case, algorithm):
    name, doc = case
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the CLI prints a warning as one line; it is not a failure
        try:
            table = load_and_run(doc, algorithm)
        except InputError as e:
            assert e.field and "\n" not in str(e), str(e)
            return
    assert "MAE(state)" in table


# --------------------------------------------------------------------------
# the command line itself
# --------------------------------------------------------------------------
def _set(name, path, value):
    doc = copy.deepcopy(SHIPPED[name])
    _parent(doc, path)[path[-1]] = value
    return doc


def _rename(name, path, new):
    doc = copy.deepcopy(SHIPPED[name])
    parent = _parent(doc, path)
    parent[new] = parent.pop(path[-1])
    return doc


CLI_CASES = {  # doc, field named in the error (None: the run succeeds)
    "omega nan": (_set("quadrants", ("model", "omega"), math.nan), "model.omega"),
    "negative range": (_set("dynamic", ("topology", "range"), -120.0), "topology.range"),
    "period zero": (_set("dynamic", ("agents", 5, "period"), 0), "agents[5].period"),
    "misspelled key": (_rename("quadrants", ("estimator", "eps"), "epss"), "estimator.epss"),
    "id 2^64": (_set("dynamic", ("agents", 0, "id"), 2**64), "agents[0].id"),
    "steps as float": (_set("quadrants", ("steps",), 200.5), "steps"),
    "too many agents": (_set("random-geometric", ("generate", "agents"), 10**6), "size"),
    "text in a matrix": (_set("quadrants", ("model", "Q"), [["a", 0.0], [0.0, 0.2]]), "model.Q"),
    "range inf runs": (_set("dynamic", ("topology", "range"), math.inf), None),
    "integer omega runs": (_set("quadrants", ("model", "omega"), 0), None),
}


@pytest.mark.parametrize("case", list(CLI_CASES))
def test_cli_on_mutated_scenarios(case, tmp_path):
    doc, field = CLI_CASES[case]
    path = tmp_path / "s.toml"
    path.write_text(to_toml(doc))
    out = tmp_path / "r.json"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    p = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "experiment", "--scenario", str(path), "--ticks",
                        str(STEPS), "--seeds", "1", "--algorithms", "diskf", "--quiet", "--json", str(out)],
                       capture_output=True, text=True, env=env, timeout=120)
    if field is None:
        assert p.returncode == 0, p.stderr
        assert json.loads(out.read_text())["diskf"]
        return
    assert p.returncode == 2, p.stderr
    assert p.stderr.count("\n") == 1 and p.stderr.startswith(f"error: {field}"), p.stderr
    assert p.stdout == "" and not out.exists()


def test_a_generated_network_too_large_for_its_links_is_refused_before_the_ticks_are_known():
    """The agent count alone bounds the generated layout's links, (N, N)
    bools; the ticks and seeds a command runs are checked with the run,
    against the largest neighbourhood where the worst case (every agent
    hearing every other) would not fit: 10,000 agents load and 20 ticks of
    one seed fit, 100 seeds do not."""
    from diskf_mesh.data.scenario import MEMORY_BOUND, load_scenario, range_links, simulation_bytes

    scn = load_scenario("random-geometric", agents=10000).with_overrides(steps=20)
    D = scn.largest_neighbourhood(20)
    assert 500 < D < 2000
    assert simulation_bytes(10000, 20, 2, 2, 1) > MEMORY_BOUND >= simulation_bytes(10000, 20, 2, 2, 1, degree=D)
    scn.check_size(1)
    with pytest.raises(InputError, match="10000 agents x 20 ticks x 100 seeds need about"):
        scn.check_size(100)
    with pytest.raises(InputError, match="50000 agents need about 2.3 GiB for their links alone"):
        load_scenario("random-geometric", agents=50000)
    small = load_scenario("random-geometric", agents=500)
    links = range_links(small.positions(1)[0], small.comm_range)
    assert small.largest_neighbourhood(1) == links.sum(axis=-1).max()
