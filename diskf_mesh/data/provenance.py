"""What produced a result file: one ``provenance`` object, the same keys in
every result the package writes (``experiment --json``, ``up --json`` and
``--estimates``, ``replay --out``, ``report``'s ``results.json``, and a
recording's ``/run`` channel), so a number can be traced to the run that
made it and the run repeated.

Keys (``KEYS``):

    command       the command line, as a list of arguments
    scenario      {"name", "sha256"}: the scenario's name and a SHA-256 of
                  its content as loaded (every field, overrides applied);
                  a list of them for the report; for a replay, the trace's
                  scenario name and the SHA-256 of the trace
    seeds         the simulation seeds
    ticks         ticks per run
    estimator     the estimator name, or a list of them
    settings      the estimator settings (``Params``) in effect
    faults        the fault settings ({} for none)
    versions      diskf-mesh, python, numpy, eclipse-zenoh
    git_commit    the commit of the checkout the package runs from, or None
    started       the run's start, ISO 8601 UTC
    status        the run's status when the writer knows it, else None
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np

KEYS = ("command", "scenario", "seeds", "ticks", "estimator", "settings", "faults", "versions", "git_commit",
        "started", "status")
DISTRIBUTIONS = ("numpy", "eclipse-zenoh")
KEY = "provenance"  # the key of a result document that holds it


def now() -> str:
    """The current time, ISO 8601 UTC to the second (a run's ``started``)."""
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def _plain(obj):
    """``obj`` as JSON-able Python: dataclasses, numpy arrays and scalars,
    tuples; non-finite floats as strings (so the hash sees them)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return _plain(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return repr(obj)
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return repr(obj)


def content_hash(obj) -> str:
    """SHA-256 (hex) of ``obj``'s content: canonical JSON of its fields."""
    text = json.dumps(_plain(obj), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def scenario_ref(scn) -> dict:
    """{"name", "sha256"} of a loaded ``Scenario``."""
    return {"name": scn.name, "sha256": content_hash(scn)}


def versions() -> dict:
    """The versions that decide a run's numbers."""
    from diskf_mesh import __version__

    out = {"diskf-mesh": __version__, "python": platform.python_version()}
    for dist in DISTRIBUTIONS:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def git_commit(start: Path | None = None) -> str | None:
    """The commit of the git checkout holding the package, or None when it
    is installed elsewhere (or git is missing)."""
    here = (start or Path(__file__)).resolve()
    for folder in here.parents:
        # the checkout of this package: its root holds .git and the package itself (a venv inside
        # another project's checkout is not that project's commit)
        if (folder / ".git").exists() and here.is_relative_to(folder / "diskf_mesh"):
            try:
                done = subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"], capture_output=True,
                                      text=True, timeout=5)
            except (OSError, subprocess.SubprocessError):
                return None
            return (done.stdout.strip() or None) if done.returncode == 0 else None
        if (folder / ".git").exists():
            return None
    return None


def command_line(argv=None) -> list:
    """The command as typed: ``diskf-mesh`` and its arguments."""
    if argv is None:
        argv = sys.argv[1:]
    return ["diskf-mesh", *(str(a) for a in argv)]


def record(*, scenario, seeds, ticks: int, estimator, settings=None, faults=None, status: str | None = None,
           started: str | None = None, argv=None, command: list | None = None) -> dict:
    """The provenance object of a result (``KEYS``, in that order).
    ``scenario``: a loaded ``Scenario`` (or an already made {"name",
    "sha256"}), or a list of them for a result of several scenarios;
    ``settings``, ``faults``: dataclasses or dicts; ``command``: the
    command line when it is not ``diskf-mesh`` and ``argv`` (the Python
    API gives the interpreter's)."""
    one = lambda s: s if isinstance(s, dict) else scenario_ref(s)  # noqa: E731
    ref = [one(s) for s in scenario] if isinstance(scenario, (list, tuple)) else one(scenario)
    return {
        "command": list(command) if command is not None else command_line(argv),
        "scenario": ref,
        "seeds": [int(s) for s in seeds],
        "ticks": int(ticks),
        "estimator": estimator if isinstance(estimator, str) else list(estimator),
        "settings": _plain(settings) if settings is not None else {},
        "faults": _plain(faults) if faults is not None else {},
        "versions": versions(),
        "git_commit": git_commit(),
        "started": started or now(),
        "status": status,
    }


def attach(doc: dict, prov: dict) -> dict:
    """``doc`` with its provenance as its last key (a new dict; ``doc``
    unchanged): a reader that takes a results document's first entry still
    gets its first estimator."""
    return {**{k: v for k, v in doc.items() if k != KEY}, KEY: prov}


def split(doc: dict) -> tuple[dict | None, dict]:
    """(provenance or None, the rest) of a result document."""
    rest = {k: v for k, v in doc.items() if k != KEY}
    return doc.get(KEY), rest
