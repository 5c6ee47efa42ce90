"""The resilience study: what one or two insiders' lies (``data.lies``) do
to the honest agents of the default estimator: without the screen before
fusion (``core.resilience``, ``defence``), with it alone, and with it and
the world's check as the run goes (the world replays each tick as its
reports come, names the liar and quarantines it through the live sets, as
in ``up`` and on the simulated network).

The world's column is the engine on the live sets the world announces
(``quarantine``, ``engine.verify.announced``): the world names a liar at the
first tick another agent received a lie of its (a message the engine does
not reproduce) and, its check of that tick running while the next tick is
out, cuts it off from the tick after the next. That is the run on the
simulated network bit for bit (``world_run``; ``tests/test_resilience.py``
checks the live sets and the estimates on both settings).

Per setting (Scenario 2; a 25-agent random geometric network with one and
with two insiders) and per lie (offsets 10 to 5,000 m, drifts, a shrunk
covariance, a replayed stale estimate, a false input, all from tick
``START``), the honest agents' state MAE over seeds 0..S-1 and every tick,
against the clean run's. The liar's own estimator stays honest (it fuses
its own true message), so its reports, honest or lying, change nothing an
honest agent fuses: the engine's columns hold both (``tests/test_lies.py``
checks that the honest estimates are the same bits). The world's column runs
the insiders with honest reports: the world then names a liar only once an
honest agent fused its lie, later than a lying report, which it names at
once.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from diskf_mesh.data import metrics
from diskf_mesh.data.lies import Lie
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.engine import batch
from diskf_mesh.engine.verify import announced
from diskf_mesh.estimators import DEFAULT
from diskf_mesh.mesh.simulated.simrun import simulate_run

START = 50
LAG = 2  # a liar named by the check of tick k is cut off from tick k + 2 (lockstep)
TARGET = 1.5  # honest MAE within 1.5x the clean run's
DIVERGED = 10.0  # an honest agent whose own MAE is 10x its clean one is counted as diverging
LIES = (("offset", 10.0), ("offset", 50.0), ("offset", 200.0), ("offset", 500.0), ("offset", 5000.0),
        ("drift", 0.5), ("drift", 2.0), ("shrink", 20.0), ("stale", 20.0), ("input", 50.0))
# (title, scenario, agent count, insiders: their ids, or how many of the best-connected agents)
SETTINGS = (("Scenario 2, one insider", "dynamic", None, (3,)),
            ("random geometric (25), one insider", "random-geometric", 25, 1),
            ("random geometric (25), two insiders", "random-geometric", 25, 2))


def insiders(scn, trace, chosen) -> tuple:
    """The insiders' ids: ``chosen`` itself, or that many of the agents with
    the most links over the run (ties: the smaller id), so that a lie
    reaches someone."""
    if not isinstance(chosen, int):
        return tuple(chosen)
    degree = np.broadcast_to(trace.links, (1,) + trace.links.shape[1:])[0].sum(axis=(0, 2))
    order = sorted(range(scn.N), key=lambda j: (-int(degree[j]), scn.agents[j].id))
    return tuple(sorted(scn.agents[j].id for j in order[:chosen]))


def describe(kind: str, size: float) -> str:
    return {"offset": f"offset {size:g} m", "drift": f"drift {size:g} m/tick",
            "shrink": f"covariance x1e-3, {size:g} m", "stale": f"{size:g}-tick-old estimate",
            "input": f"false input {size:g}"}[kind]


def _errors(trace, est, honest):
    """(pooled honest MAE, per honest agent MAE)."""
    e_state = metrics.errors(trace, est.agents(honest))[0]
    return float(e_state.mean()), e_state.mean(axis=(0, 1))


def quarantine(scn, trace) -> tuple:
    """(live (K, N), [(agent id, named at, cut off from)]) of a run of
    ``scn`` (its lies, their reports honest, none withheld) on ``trace``
    (one seed) with the world's check: each liar named at the first tick it
    lies to a live agent linked to it, cut off ``LAG`` ticks later."""
    links = np.asarray(trace.links[0], dtype=bool)
    K, N = links.shape[:2]
    ids = [a.id for a in scn.agents]
    live = np.ones((K, N), dtype=bool)
    cuts, named = [], set()
    for k in range(1, K + 1):
        for lie in scn.lies:
            j = ids.index(lie.agent)
            if j in named or not lie.lying(k):
                continue
            heard = links[k - 1, :, j] & live[k - 1]
            heard[j] = False
            if heard.any():
                named.add(j)
                live[k - 1 + LAG:, j] = False
                cuts.append((lie.agent, k, k + LAG))
    return live, cuts


def with_world(scn, trace, params, honest) -> tuple:
    """The honest agents' state errors (B, K, H) of ``scn``'s lies on
    ``trace`` with the world's check (``quarantine``, per seed; the seeds
    with the same links and live sets in one engine batch) and the screen
    set by ``params``, and the quarantines [(seed, agent, named at, cut off
    from)]."""
    B = len(trace.seeds)
    found = [quarantine(scn, batch.take_seeds(trace, slice(b, b + 1))) for b in range(B)]
    shared = trace.links.shape[0] == 1
    groups: dict = {}
    for b, (live, _) in enumerate(found):
        groups.setdefault((live.tobytes(), 0 if shared else b), []).append(b)
    errors = [None] * B
    for members in groups.values():
        some = batch.take_seeds(trace, np.array(members))
        est = batch.run(announced(some, found[members[0]][0]), DEFAULT, params, lies=scn.lies)
        for i, b in enumerate(members):
            errors[b] = metrics.errors(some, est.agents(honest))[0][i:i + 1]
    cuts = [(int(trace.seeds[b]),) + c for b, (_, cs) in enumerate(found) for c in cs]
    return np.concatenate(errors), cuts


def world_run(scn, seed: int, honest) -> tuple:
    """The run of ``scn`` (its lies and settings) on the simulated network
    with seed ``seed``, the world checking as the run goes: (the honest
    agents' state errors (1, K, H), the quarantines [(seed, agent, named at,
    cut off from)], the status). Every honest agent-tick must be reported
    (else ``RuntimeError``: the study's numbers would not be what the
    algorithm computed)."""
    trace = simulate(scn, [seed])
    run = simulate_run(scn, trace, DEFAULT, seed)
    rec = run.record
    if not rec.reported[:, honest].all():
        raise RuntimeError(f"resilience: seed {seed}: an honest agent's report is missing ({run.status.reason})")
    e_state = metrics.errors(trace, rec.estimates(fill=True).agents(honest))[0]
    return e_state, [(seed, q["agent"], q["tick"], q["from"]) for q in rec.quarantined], run.status.status


def measure(seeds, steps=None, progress=None) -> list:
    """One row per (setting, lie): the clean honest MAE, the MAE with the
    lie without the screen, with it, and with it and the world's check
    (``with_world``), and the worst honest agent's ratio to its clean MAE.
    ``progress(1)`` after each cell."""
    rows = []
    for title, name, agents, chosen in SETTINGS:
        scn = load_scenario(name, agents=agents).with_overrides(steps=steps)
        trace = simulate(scn, list(seeds))
        liars = insiders(scn, trace, chosen)
        title = f"{title} (agent{'s' if len(liars) > 1 else ''} {', '.join(map(str, liars))})"
        honest = [j for j, a in enumerate(scn.agents) if a.id not in liars]
        modes = {"off": dataclasses.replace(scn.params, defence=False),
                 "on": dataclasses.replace(scn.params, defence=True)}
        clean, clean_agents = _errors(trace, batch.run(trace, DEFAULT, modes["on"]), honest)
        for kind, size in LIES:
            lying = scn.with_lies([Lie(i, kind, size, start=START) for i in liars])
            row = {"setting": title, "kind": kind, "size": size, "lie": describe(kind, size), "clean": clean}
            for mode, params in modes.items():
                try:
                    mae, per_agent = _errors(trace, batch.run(trace, DEFAULT, params, lies=lying.lies), honest)
                    worst = float(np.max(per_agent / clean_agents))
                except np.linalg.LinAlgError:
                    mae, worst = float("inf"), float("inf")
                row[mode], row[f"worst_{mode}"] = mae, worst
            e_state, row["cut"] = with_world(lying, trace, modes["on"], honest)
            row["world"] = float(e_state.mean())
            row["worst_world"] = float(np.max(e_state.mean(axis=(0, 1)) / clean_agents))
            row["seeds"] = len(trace.seeds)
            rows.append(row)
            if progress is not None:
                progress(1)
    return rows


def misses(row, mode: str) -> bool:
    """Whether ``row``'s honest MAE in ``mode`` ("on": the screen, "world":
    the screen and the world's check) misses the target, or an honest agent
    diverges there."""
    return not (row[mode] <= TARGET * row["clean"]) or not (row[f"worst_{mode}"] < DIVERGED)


def missing(rows, mode: str = "world") -> list:
    """The rows that miss the target in ``mode`` (``misses``); the world's
    column where the rows have it, else the screen's."""
    if mode == "world" and rows and "world" not in rows[0]:
        mode = "on"
    return [r for r in rows if misses(r, mode)]


def quarantines(row) -> str:
    """The world's cuts of ``row``: the ticks each insider was named at and
    cut off from over the seeds, and in how many seeds."""
    cuts, seeds = row["cut"], row["seeds"]
    if not cuts:
        return f"none (0 of {seeds})"
    named, cut = [c[2] for c in cuts], [c[3] for c in cuts]
    span = lambda v: f"{min(v)}" if min(v) == max(v) else f"{min(v)}-{max(v)}"  # noqa: E731
    return f"named {span(named)}, cut from {span(cut)} ({len({c[0] for c in cuts})} of {seeds})"


def table(rows) -> str:
    """The markdown table."""
    world = bool(rows) and "world" in rows[0]
    ratio = lambda r, m: f"{r[m]:.2f} ({r[m] / r['clean']:.2f}x)"  # noqa: E731
    mark = lambda r, m: "met" if not misses(r, m) else "**missed**"  # noqa: E731
    head = "| setting | lie | clean | without the screen | screen only | worst honest agent | target |"
    rule = "|---|---|---:|---:|---:|---:|:---:|"
    if world:
        head += " screen and the world's check | worst honest agent | the world's quarantine | target |"
        rule += "---:|---:|---|:---:|"
    out = [head, rule]
    for r in rows:
        line = (f"| {r['setting']} | {r['lie']} | {r['clean']:.2f} | {ratio(r, 'off')} | {ratio(r, 'on')} "
                f"| {r['worst_on']:.2f}x | {mark(r, 'on')} |")
        if world:
            line += f" {ratio(r, 'world')} | {r['worst_world']:.2f}x | {quarantines(r)} | {mark(r, 'world')} |"
        out.append(line)
    return "\n".join(out)


BEGIN, END = "<!-- resilience table: diskf-mesh resilience -->", "<!-- end of the resilience table -->"


def write(rows, out, command: str) -> tuple:
    """The table into ``out``/security.md between its markers (``BEGIN``,
    ``END``) if it has them, else ``out``/resilience.md; the figure into
    ``out``/figures/resilience.png; the numbers into ``out``/resilience.json.
    Returns the paths written."""
    import json

    from diskf_mesh.data.outputs import save_json

    block = f"{BEGIN}\n\n{table(rows)}\n\nMade by `{command}`.\n\n{END}"
    doc = out / "security.md"
    text = doc.read_text() if doc.exists() else ""
    if BEGIN in text and END in text:
        head, _, rest = text.partition(BEGIN)
        _, _, tail = rest.partition(END)
        target, text = doc, head + block + tail
    else:
        target, text = out / "resilience.md", f"# Resilience to insiders\n\n{block}\n"
    target.write_text(text)
    (out / "figures").mkdir(exist_ok=True)
    fig = out / "figures" / "resilience.png"
    figure(rows, fig)
    numbers = out / "resilience.json"
    save_json(str(numbers), json.loads(json.dumps(rows, default=float)), "json")
    return target, fig, numbers


def figure(rows, path) -> None:
    """Honest MAE (x the clean run's) against the offset's size, without the
    screen, with it, and with it and the world's check, one colour per
    setting."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    titles = list(dict.fromkeys(r["setting"] for r in rows))
    for title, color in zip(titles, ("tab:blue", "tab:orange", "tab:green")):
        pts = [r for r in rows if r["setting"] == title and r["kind"] == "offset"]
        sizes = [r["size"] for r in pts]
        ax.plot(sizes, [r["off"] / r["clean"] for r in pts], "--o", color=color, alpha=0.5,
                label=f"{title}: no screen")
        ax.plot(sizes, [r["on"] / r["clean"] for r in pts], "-s", color=color, alpha=0.8, label=f"{title}: screen")
        if "world" in pts[0]:
            ax.plot(sizes, [r["world"] / r["clean"] for r in pts], ":^", color=color, lw=2,
                    label=f"{title}: screen and the world's check")
    ax.axhline(TARGET, color="grey", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("the insider's offset (m)")
    ax.set_ylabel("honest MAE / clean run's")
    ax.set_title(f"{DEFAULT}: honest error against an insider's offset (from tick {START})")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
