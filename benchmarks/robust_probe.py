"""Probe: state/input MAE and NEES (all agent-ticks, and where the neighbourhood measures) of every
estimator and the centralized bound in every setting (engine, 20 seeds; ``python benchmarks/robust_probe.py [S]``).
``run([..., ("label", "diskf-r", robust(gate=False))])`` adds variant rows."""
import sys, time
from dataclasses import replace
import numpy as np
from diskf_mesh.engine import batch as engine
from diskf_mesh.data import metrics
from diskf_mesh.engine import centralized
from diskf_mesh.data.scenario import load_scenario, simulate

SEEDS = range(int(sys.argv[1]) if len(sys.argv) > 1 else 20)

def settings(which="all"):
    out = []
    s1 = load_scenario("quadrants")
    for t in ("all", "ring", "none"):
        out.append((f"S1 {t}", s1.with_overrides(topology=t)))
    s2 = load_scenario("dynamic")
    for r in (0, 30, 60, 90, 120, 150, 180, 210, 240, 270, 300):
        out.append((f"S2 r{r}", s2.with_overrides(topology="range", comm_range=float(r))))
    out.append(("S2 all", s2.with_overrides(topology="all")))
    if which == "all":
        out.append(("RGG", load_scenario("random-geometric")))
    return out

def row(tr, est):
    e_s, e_i, nees = metrics.errors(tr, est)
    s = metrics.summarize(e_s, e_i, nees)
    # NEES where the neighbourhood measures
    L = np.broadcast_to(tr.links, tr.has.shape[:2] + tr.links.shape[2:]) if tr.links.shape[0] == tr.has.shape[0] else np.broadcast_to(tr.links[0], tr.has.shape[1:2] + tr.links.shape[2:])
    heard = np.einsum("...kij,bkj->bki", L.astype(float), tr.has.astype(float)) > 0
    s["nees_obs"] = float(nees[heard].mean()) if heard.any() else float("nan")
    return s

def run(algs, which="all", params_for=None):
    res = {}
    for name, scn in settings(which):
        tr = simulate(scn, SEEDS)
        res[name] = {}
        for a in algs:
            if a == "centralized":
                est = centralized.run_centralized(tr)
            else:
                label, alg, p = a if isinstance(a, tuple) else (a, a, scn.params)
                est = engine.run(tr, alg, p(scn.params) if callable(p) else p)
                a = label
            res[name][a] = row(tr, est)
    return res

def show(res, keys=("mae_state", "mae_input", "nees", "nees_obs")):
    algs = list(next(iter(res.values())))
    for key in keys:
        print(f"== {key}")
        print(f"{'':10}" + "".join(f"{a[:11]:>12}" for a in algs))
        for st, r in res.items():
            print(f"{st:10}" + "".join(f"{r[a][key]:12.2f}" for a in algs))

def robust(**kw):
    """Params -> Params with diskf-r's switches ``kw`` (for variant rows)."""
    from diskf_mesh.core.model import RobustOptions
    return lambda p: replace(p, robust=RobustOptions(**kw))


if __name__ == "__main__":
    t = time.time()
    res = run(["diskf", "diskf-r", "cdrkf", "ldrkf", "kcf", "diffkf", "gdkf", "centralized"])
    show(res)
    print("time", time.time() - t)
