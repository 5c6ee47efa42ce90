"""diskf-auto's (and diskf-r's) outputs on many cases, saved or compared bit for bit.

A change meant to make ``diskf-auto`` faster must not move a bit of what it
computes. This runs it on the engine over Table II (Scenario 1, all three
topologies, 20 seeds), every case of the held-out suite
(``studies.heldout.cases``: 2 seeds, the first ``--ticks`` ticks), each with
the noise learning (``[estimator.auto] noise``) and the screen (``defence``)
off and on (every fourth case in all four settings, the rest with both off),
and one agent at a time as an agent process runs it
(``mesh.protocol.estimator.lockstep``) on a few of them; then either saves
every output (``--save FILE``, an ``.npz``) or compares them with a saved
file (``--check FILE``) with ``np.array_equal`` and exits 1 on any
difference, naming the cases that differ. ``diskf-r`` and the centre with
its input model (``engine.centralized.run_centralized_persist``), which
share its joint steps (``equations.replace_marginal``, ``input_to_state``),
run on Table II and every eighth case.

    git archive BASE | tar -x -C /tmp/base
    PYTHONPATH=/tmp/base python benchmarks/auto_bits.py --save /tmp/auto.npz
    python benchmarks/auto_bits.py --check /tmp/auto.npz

``--auto NAME=VALUE`` (repeatable) sets ``[estimator.auto]`` options on every
``diskf-auto`` run, to check an opt-in mode (``--auto noise_span=10``,
``--auto noise_level=10``); where an option may not go with the noise
learning, the settings with it are left out.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

import numpy as np

from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine.centralized import run_centralized_persist
from diskf_mesh.studies.experiment import run_or_none
from diskf_mesh.mesh.protocol.estimator import lockstep
from diskf_mesh.studies import heldout

NAME = "diskf-auto"
SETTINGS = {"": (False, False), "noise": (True, False), "defence": (False, True), "noise+defence": (True, True)}


def with_settings(params, noise: bool, defence: bool, auto: dict):
    return replace(params.with_setting("auto", noise=noise, **auto), defence=defence)


def settings(auto: dict) -> dict:
    """The (noise, defence) settings to run: those the options ``auto``
    allow (``noise_level`` and ``noise_span`` go without the noise
    learning)."""
    alone = "noise_level" in auto or "noise_span" in auto
    return {tag: s for tag, s in SETTINGS.items() if not (alone and s[0])}


def engine_outputs(tr, params, name: str = NAME) -> list:
    est = run_or_none(tr, name, params)
    return [np.array([np.nan])] if est is None else [est.x, est.P, est.d, est.d_valid]


def agent_outputs(scn, tr) -> list:
    """One agent at a time; a run that fails (a covariance not positive
    definite) is [NaN], as ``engine_outputs`` gives it, so that it compares
    equal only to a run that failed too."""
    xs, Ps, ds, dv = [], [], [], []
    try:
        for _, _, outs in lockstep(scn, NAME, tr):
            for o in outs.values():
                xs.append(o.x), Ps.append(o.P), ds.append(o.d), dv.append(o.d_valid)
    except np.linalg.LinAlgError:
        return [np.array([np.nan])]
    return [np.array(xs), np.array(Ps), np.array(ds), np.array(dv)]


def robust(label: str, scn, tr):
    """diskf-r and the centre with its input model on one case."""
    yield f"{label} diskf-r", engine_outputs(tr, scn.params, "diskf-r")
    est = run_centralized_persist(tr, scn.params.robust)
    yield f"{label} centre", [est.x, est.P, est.d, est.d_valid]


def outputs(ticks: int, auto: dict | None = None):
    """Yields (label, [arrays]) for every case; ``auto``: ``[estimator.auto]``
    options for every ``diskf-auto`` run."""
    auto = auto or {}
    runs = settings(auto)
    both = [tag for tag in ("", "noise+defence", "defence") if tag in runs][:2]
    q = load_scenario("quadrants")
    for topology in ("all", "ring", "none"):
        scn = q.with_overrides(topology=topology)
        tr = simulate(scn, range(20))
        for tag in both:
            yield f"Table II {topology} {tag}", engine_outputs(tr, with_settings(scn.params, *SETTINGS[tag], auto))
        yield from robust(f"Table II {topology}", scn, tr)
    for i, case in enumerate(heldout.cases()):
        scn, tr = case.simulate(range(2), ticks)
        for tag, (noise, defence) in runs.items():
            if tag and i % 4:
                continue
            if auto and scn.model(ticks).m > 1 and "noise_level" in auto:
                continue  # noise_level needs one bank (DISKFAuto.refuse)
            yield f"{case.label} {tag}", engine_outputs(tr, with_settings(scn.params, noise, defence, auto))
        if i % 8 == 0:
            yield from robust(case.label, scn, tr)
        if i % 16 == 0 and len(scn.agents) <= 9:
            for tag in both:
                p = with_settings(scn.params, *SETTINGS[tag], auto)
                yield f"{case.label} {tag} agent", agent_outputs(scn.with_overrides(params=p), tr)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--save", metavar="FILE")
    what.add_argument("--check", metavar="FILE")
    ap.add_argument("--ticks", type=int, default=60)
    ap.add_argument("--auto", action="append", default=[], metavar="NAME=VALUE",
                    help="an [estimator.auto] option for every diskf-auto run (repeatable)")
    a = ap.parse_args(argv)
    auto = {}
    for item in a.auto:
        name, sep, value = item.partition("=")
        try:
            auto[name] = float(value)
        except ValueError:
            sep = ""
        if not sep:
            print(f"error: --auto {item!r}: expected NAME=NUMBER", file=sys.stderr)
            return 2
    saved = None if a.check is None else np.load(a.check)
    found, differ, t0 = {}, [], time.process_time()
    for n, (label, arrays) in enumerate(outputs(a.ticks, auto)):
        for j, arr in enumerate(arrays):
            key = f"{label} #{j}"
            found[key] = arr
            if saved is not None and (key not in saved.files or not np.array_equal(saved[key], arr, equal_nan=True)):
                differ.append(key)
        if n % 20 == 0:
            print(f"{n} cases, {time.process_time() - t0:.0f} s CPU, {len(differ)} differ", file=sys.stderr, flush=True)
    if saved is None:
        np.savez(a.save, **found)
        print(f"{len(found)} arrays saved to {a.save}")
        return 0
    missing = sorted(set(saved.files) - set(found))
    for key in differ + missing:
        print("differs" if key in found else "missing", key)
    print(f"{len(found)} arrays compared: {len(differ)} differ, {len(missing)} missing")
    return 1 if differ or missing else 0


if __name__ == "__main__":
    raise SystemExit(main())
