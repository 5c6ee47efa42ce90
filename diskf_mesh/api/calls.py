"""The public calls (docs/api.md): a scenario in, a trace out; a trace and
an estimator in, estimates and metrics out; a whole experiment; a replay; a
mesh run of real processes. Each returns a ``results`` dataclass."""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from dataclasses import replace
from os import PathLike
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence, Union

from diskf_mesh import estimators as _estimators
from diskf_mesh.api.results import Experiment, MeshRun, Run
from diskf_mesh.core.errors import InputError
from diskf_mesh.data import metrics as _metrics
from diskf_mesh.data import provenance as _provenance
from diskf_mesh.data import scenario as _scenario
from diskf_mesh.data.outputs import save_json
from diskf_mesh.data.trace import Trace, estimator_from_json, read_trace_file, trace_from_json, trace_to_json
from diskf_mesh.engine import batch as _engine
from diskf_mesh.estimators import Params

ScenarioLike = Union[str, "PathLike[str]", _scenario.Scenario]
TraceLike = Union[str, "PathLike[str]", Trace, Mapping[str, Any]]


def _command() -> list:
    """The command line of a Python process using the API."""
    return ["python", *sys.argv]


def _seeds(seeds: int | Iterable[int]) -> list[int]:
    """``seeds``: a count (seeds 0..count-1) or the seeds themselves."""
    if isinstance(seeds, int):
        if seeds < 1:
            raise InputError("seeds", f"must be at least 1, got {seeds}")
        return list(range(seeds))
    out = [int(s) for s in seeds]
    if not out or min(out) < 0:
        raise InputError("seeds", "give at least one seed, each >= 0")
    return out


def _params(base: Params, settings: Params | Mapping[str, Any] | None) -> Params:
    """The estimator settings: ``base`` (the scenario's or the trace's),
    replaced by a whole ``Params`` or updated by a mapping of fields."""
    if settings is None:
        return base
    if isinstance(settings, Params):
        return settings
    unknown = sorted(set(settings) - set(vars(base)))
    if unknown:
        raise InputError(f"settings.{unknown[0]}", f"unknown estimator setting; known: {', '.join(sorted(vars(base)))}")
    try:
        return replace(base, **dict(settings))
    except ValueError as e:
        key, _, msg = str(e).partition(": ")
        raise InputError(f"settings.{key}", msg) from None


def _estimator(name: str) -> str:
    """``name`` if it is a registered estimator; else InputError naming the known ones."""
    try:
        _estimators.get(name)
    except ValueError as e:
        raise InputError("estimator", str(e)) from None
    return name


def estimator_names() -> tuple[str, ...]:
    """Every registered estimator's name (built-ins and installed plugins)."""
    return tuple(_estimators.NAMES)


def load_scenario(scenario: ScenarioLike, *, agents: int | None = None) -> _scenario.Scenario:
    """A scenario by shipped name (``quadrants``, ``dynamic``,
    ``random-geometric``) or a path to your own TOML file (docs/formats.md);
    a ``Scenario`` is returned as it is. ``agents``: the number of agents of
    a generated scenario."""
    if isinstance(scenario, _scenario.Scenario):
        return scenario
    return _scenario.load_scenario(str(scenario), agents=agents)


def simulate(scenario: ScenarioLike, *, seeds: int | Iterable[int] = (0,), steps: int | None = None,
             topology: str | None = None, comm_range: float | None = None) -> Trace:
    """Ground truth, measurements and links of ``scenario`` for each seed
    (``seeds``: a count or the seeds), ``steps`` ticks (default: the
    scenario's); ``topology`` (all, ring, none, range) and ``comm_range``
    override the scenario's."""
    scn = load_scenario(scenario).with_overrides(topology=topology, comm_range=comm_range, steps=steps)
    return _scenario.simulate(scn, _seeds(seeds))


def estimate(trace: TraceLike, estimator: str = _estimators.DEFAULT, *,
             settings: Params | Mapping[str, Any] | None = None, scenario: _scenario.Scenario | None = None) -> Run:
    """Run ``estimator`` on every seed of ``trace`` (a ``Trace``, a
    diskf-trace/1 document or its path) in-process, on the batched engine.
    ``settings`` replace or update the estimator settings the trace (or
    ``scenario``) carries; metrics when the trace has truth."""
    started = _provenance.now()
    doc = None
    if not isinstance(trace, Trace):
        if isinstance(trace, (str, PathLike)):
            doc, trace = read_trace_file(trace)
        else:
            doc = dict(trace)
            trace = trace_from_json(doc)
    base = scenario.params if scenario is not None else (estimator_from_json(doc) if doc is not None else Params())
    params = _params(base, settings)
    est = _engine.run(trace, _estimator(estimator), params)
    scores = _metrics.compute(trace, est) if trace.truth_x is not None else None
    if scenario is not None:
        ref = _provenance.scenario_ref(scenario)
    elif doc is not None:
        ref = {"name": doc.get("scenario"), "sha256": _provenance.content_hash(doc)}
    else:
        ref = {"name": None, "sha256": _provenance.content_hash(trace)}
    prov = _provenance.record(scenario=ref, seeds=trace.seeds, ticks=trace.shape[1], estimator=estimator,
                              settings=params, faults=scenario.faults if scenario is not None else None,
                              status="done", started=started, command=_command())
    return Run(estimator, trace, est.x, est.P, est.d, est.d_valid, scores, prov)


def run(scenario: ScenarioLike, estimator: str = _estimators.DEFAULT, *, seeds: int | Iterable[int] = (0,),
        steps: int | None = None, settings: Params | Mapping[str, Any] | None = None,
        topology: str | None = None, comm_range: float | None = None) -> Run:
    """``simulate`` then ``estimate``: one estimator on a scenario, in-process."""
    scn = load_scenario(scenario).with_overrides(topology=topology, comm_range=comm_range, steps=steps)
    return estimate(_scenario.simulate(scn, _seeds(seeds)), estimator, settings=settings, scenario=scn)


def experiment(scenario: ScenarioLike, estimators: Sequence[str] | str = "all", *,
               topologies: Sequence[str] | None = None, comm_range: float | None = None,
               seeds: int | Iterable[int] = 20, steps: int | None = None,
               settings: Params | Mapping[str, Any] | None = None) -> Experiment:
    """What ``diskf-mesh experiment`` computes: every estimator of
    ``estimators`` ("all", a comma list or a sequence of names) on every
    topology of ``topologies`` (default: a range-gated scenario's own range,
    else all, ring and none) over ``seeds`` (a count or the seeds)."""
    from diskf_mesh.studies import experiment as _experiment

    started = _provenance.now()
    scn = load_scenario(scenario)
    names = [n.strip() for n in estimators.split(",")] if isinstance(estimators, str) else list(estimators)
    names = list(_estimators.ALL) if names == ["all"] else [_estimator(n) for n in names]
    if topologies is None:
        if comm_range is not None:
            topologies = ["range"]
        elif scn.topology == "range":
            topologies, comm_range = ["range"], scn.comm_range
        else:
            topologies = ["all", "ring", "none"]
    seed_list = _seeds(seeds)
    params = _params(scn.params, settings)
    results = _experiment.run_experiment(scn, _experiment.settings_for(topologies, comm_range), names, seed_list,
                                         steps, params)
    prov = _provenance.record(scenario=scn, seeds=seed_list, ticks=steps or scn.steps, estimator=names,
                              settings=params, faults=scn.faults, status="done", started=started,
                              command=_command())
    return Experiment(results, prov)


def replay(source: TraceLike, estimator: str = _estimators.DEFAULT, *,
           settings: Params | Mapping[str, Any] | None = None) -> Run:
    """A recorded run again: a diskf-trace/1 trace (path, document or
    ``Trace``) with ``estimator``, or a recording of ``up --record``
    (``RUN.mcap``) on exactly what each agent fused, with the recording's
    estimator and settings (``Run.equal``: reproduced bit for bit, the
    recording whole; for one cut or damaged, False and the provenance's
    status says why)."""
    if isinstance(source, (str, PathLike)) and str(source).endswith(".mcap"):
        return _replay_recording(Path(source))
    return estimate(source, estimator, settings=settings)


def _replay_recording(path: Path) -> Run:
    from diskf_mesh.recording.reader import read, take_ticks
    from diskf_mesh.recording.replay import compare
    from diskf_mesh.recording.replay import replay as replay_fused

    started = _provenance.now()
    rec = read(path)
    if not rec.ticks:
        raise InputError("recording", f"{path} holds no complete tick to replay")
    est = replay_fused(rec)
    trace = take_ticks(rec.trace, rec.ticks)
    scores = _metrics.compute(trace, est) if trace.truth_x is not None else None
    equal, why = compare(rec, est).equal, rec.not_whole()
    made = rec.run.get("provenance") or {}
    prov = _provenance.record(scenario=made.get("scenario") or {"name": rec.run.get("scenario_name"), "sha256": None},
                              seeds=[rec.run.get("seed", 0)], ticks=rec.ticks, estimator=rec.algorithm,
                              settings=rec.run.get("params"), faults=rec.run.get("faults"),
                              status=f"not whole: {why}" if why else "equal" if equal else "differs", started=started, command=_command())
    return Run(rec.algorithm, trace, est.x, est.P, est.d, est.d_valid, scores, prov, equal and not why)


def read_trace(path: str | PathLike[str]) -> Trace:
    """A diskf-trace/1 file, checked against its schema (docs/formats.md)."""
    return read_trace_file(path)[1]


def write_trace(trace: Trace, path: str | PathLike[str], *, seed_index: int = 0, scenario: str | None = None,
                settings: Params | None = None) -> None:
    """One seed of ``trace`` as a diskf-trace/1 file (what ``simulate --out``
    writes), atomically."""
    save_json(path, trace_to_json(trace, seed_index, scenario=scenario, params=settings))


def up(scenario: str | PathLike[str] = "dynamic", *, ticks: int | None = None, estimator: str = _estimators.DEFAULT,
       seed: int = 0, flags: Sequence[str] = (), timeout: float | None = None) -> MeshRun:
    """``diskf-mesh up``: the world and one OS process per agent over Zenoh
    on this host, in a child process. ``flags``: more of ``up``'s flags
    (``--loss 0.2``, ``--record run.mcap``, ``--rate 25``, ...). Returns the
    exit status, the results and the estimates document; raises
    ``subprocess.TimeoutExpired`` after ``timeout`` seconds."""
    with tempfile.TemporaryDirectory(prefix="diskf-api-") as tmp:
        res, est = Path(tmp) / "results.json", Path(tmp) / "estimates.json"
        argv = [sys.executable, "-m", "diskf_mesh.cli.main", "up", "--scenario", str(scenario),
                "--algorithm", estimator, "--seed", str(seed), "--json", str(res), "--estimates", str(est),
                "--quiet", *(["--ticks", str(ticks)] if ticks is not None else []), *map(str, flags)]
        done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
        load = lambda p: json.loads(p.read_text()) if p.exists() else None  # noqa: E731
        return MeshRun(done.returncode, load(res), load(est), done.stderr)
