"""Random linear models nobody tuned on: how often each estimator diverges.
Prints a table; not a test.

    python benchmarks/random_models.py [--models 240] [--first 0] [--ticks 100] [--estimators a,b]

Model ``s`` is drawn from ``numpy.random.default_rng(s)``: n = 2..4 states,
m = 1..2 inputs (m <= n), dynamics a rotation (with decay), a constant
velocity chain or a random matrix of spectral radius 0.8..1.02; G random;
Q = q I with q = 10^U(-4, 1); 3..6 agents, each measuring 1..2 states (or
random combinations of them) with R = r I, r = 10^U(-3, 3); all-to-all, ring
or isolated; a step, sine, white, telegraph, ramp or constant input of
amplitude 10^U(-2, 1). Every estimator runs on seeds 0 and 1 through the
engine; a run counts as diverged where ``studies.experiment.run_or_none``
says so (its covariance lost positive definiteness, or an estimate left
``wire.MAX_ABS``). The models listed for an estimator reproduce with
``--first S --models 1``.
"""
from __future__ import annotations

import argparse
import sys
from collections import defaultdict

import numpy as np

from diskf_mesh import estimators as algorithms
from diskf_mesh.data.argtypes import add_ticks
from diskf_mesh.data.scenario import parse_scenario, simulate
from diskf_mesh.studies import experiment


def random_raw(s: int, steps: int) -> dict:
    """Scenario table of random model ``s`` (module docstring)."""
    rng = np.random.default_rng(s)
    n = int(rng.choice([2, 3, 4]))
    m = int(rng.integers(1, min(n, 2) + 1))
    kind = rng.choice(["rotation", "velocity", "random"])
    if kind == "rotation":
        w = rng.uniform(0.02, 0.8)
        A = np.eye(n) * rng.uniform(0.9, 1.0)
        A[:2, :2] = [[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]]
    elif kind == "velocity":
        dt = rng.uniform(0.1, 1.0)
        A = np.eye(n)
        for i in range(0, n - 1, 2):
            A[i, i + 1] = dt
    else:
        M = rng.normal(size=(n, n))
        A = M / max(abs(np.linalg.eigvals(M))) * rng.uniform(0.8, 1.02)
    G = rng.normal(size=(n, m))
    Q = 10 ** rng.uniform(-4, 1) * np.eye(n)
    r = 10 ** rng.uniform(-3, 3)
    agents = []
    for i in range(int(rng.integers(3, 7))):
        p = int(rng.integers(1, min(n, 2) + 1))
        H = rng.normal(size=(p, n)) if rng.random() < 0.3 else np.eye(n)[rng.choice(n, p, replace=False)]
        agents.append(dict(id=i + 1, H=H.tolist(), R=(r * rng.uniform(0.5, 2) * np.eye(p)).tolist(), sense="always",
                           position=[float(i), 0.0]))
    amp = float(10 ** rng.uniform(-2, 1))
    inp = rng.choice(["step", "sine", "white", "telegraph", "ramp", "constant"])
    table = {"step": dict(kind="step", at=int(rng.integers(1, 50)), after=[amp] * m),
             "sine": dict(kind="sine", amplitude=[amp] * m, period=float(rng.uniform(4, 80))),
             "white": dict(kind="white", scale=[amp] * m, seed=int(rng.integers(0, 99))),
             "telegraph": dict(kind="telegraph", amplitude=[amp] * m, interval=float(int(rng.integers(2, 20)))),
             "ramp": dict(kind="ramp", slope=[amp / 50] * m),
             "constant": dict(kind="constant", value=[amp] * m)}[inp]
    return dict(name=f"random-{s}", steps=steps,
                model=dict(dynamics="matrix", A=A.tolist(), G=G.tolist(), Q=Q.tolist(), x0=rng.normal(size=n).tolist(),
                           P0=np.eye(n).tolist(), position_dims=[0, 1]),
                topology=dict(kind=str(rng.choice(["all", "ring", "none"]))), agents=agents, input=table)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", type=int, default=240)
    p.add_argument("--first", type=int, default=0)
    add_ticks(p, type=int, default=100, help="ticks per model (default 100)")
    p.add_argument("--estimators", default="all", help="names, comma-separated (default: every estimator)")
    args = p.parse_args(argv)
    if args.models < 1 or args.first < 0 or args.ticks < 1:
        p.error("--models and --steps must be at least 1, --first at least 0")
    try:
        names = algorithms.parse_list(args.estimators)
    except ValueError as e:
        p.error(f"--estimators: {e}")
    diverged = defaultdict(list)
    for s in range(args.first, args.first + args.models):
        scn = parse_scenario(random_raw(s, args.ticks))
        tr = simulate(scn, [0, 1])
        for name in names:
            if experiment.run_or_none(tr, name, scn.params) is None:
                diverged[name].append(s)
        print(f"\r{s - args.first + 1}/{args.models} models", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    print(f"\n{args.models} random models (seeds {args.first}..{args.first + args.models - 1}), "
          f"{args.ticks} ticks, simulation seeds 0 and 1\n")
    print("| estimator | diverged | models |")
    print("|---|---:|---|")
    for name in names:
        models = diverged.get(name, [])
        shown = ", ".join(map(str, models[:12])) + (" ..." if len(models) > 12 else "")
        print(f"| {name} | {len(models)} | {shown} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
