"""The reproduction report: markdown from ``studies.Results`` and figures.

``render`` only formats; every number in the text comes from the results
(or from the scenario files), so a regenerated report never contradicts its
own tables. ``write_report`` runs everything and writes
``OUT/reproduction.md``, ``OUT/figures/*.png`` and ``OUT/results.json``.
"""
from __future__ import annotations

import math
import os
import subprocess
import time
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from diskf_mesh import estimators
from diskf_mesh.studies import figures, heldout
from diskf_mesh.data import paper_values
from diskf_mesh.studies import suite as studies
from diskf_mesh.data import provenance
from diskf_mesh.data.outputs import atomic_open, save_json
from diskf_mesh.studies.experiment import LABELS
from diskf_mesh.studies.pool import process_pool
from diskf_mesh.data.scenario import load_scenario

METRICS = ("mae_state", "rmse_state", "mae_input", "rmse_input")
METRIC_NAMES = {"mae_state": "MAE(state)", "rmse_state": "RMSE(state)", "mae_input": "MAE(input)",
                "rmse_input": "RMSE(input)", "input_coverage": "coverage"}
COMM_NAMES = {"all": "all-to-all", "ring": "1-hop (ring)", "none": "none"}


def comm_name(setting: str) -> str:
    """Display name of a setting label: topologies by name, ranges as such."""
    return COMM_NAMES.get(setting, f"range {setting}")


# --------------------------------------------------------------------------
# formatting
# --------------------------------------------------------------------------
def num(v, digits: int = 2) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def pm(row: dict, key: str) -> str:
    """"mean ± std", or "-" where there is no value."""
    if not math.isfinite(row[key]):
        return "-"
    return f"{num(row[key])} ± {num(row.get(f'{key}_std'))}"


def table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


BOUND = "centralized"  # a reference row, never "the best"
PBOUND = "centralized-persist"  # the bound of diskf-r's own input model, a reference row too
REFERENCES = (BOUND, PBOUND)
BOUND_LABELS = {PBOUND: "Centralized, persistent input (bound of DISKF-R's model)"}


def _label(a: str) -> str:
    return BOUND_LABELS.get(a) or LABELS.get(a, a)


PAPER_ALGS = paper_values.COLUMNS
# Who the narrative is about, from the declarations: the paper's method (the first column of its
# tables), the registered estimators that extend it (``Estimator.extends``: diskf-r), and that family
OURS = PAPER_ALGS[0]
EXTENSIONS = tuple(name for name, cls in estimators.REGISTRY.items() if cls.extends == OURS)
EXTENSION = EXTENSIONS[0] if EXTENSIONS else OURS  # the one section 10 is about
FAMILY = (OURS,) + EXTENSIONS


def best_alg(results: dict, setting: str, key: str, among=None) -> str:
    """The algorithm with the lowest value (ties: the first listed), among
    ``among`` (default: all but the centralized references)."""
    vals = {a: results[a][setting][key] for a in results if a not in REFERENCES and (among is None or a in among)}
    finite = {a: v for a, v in vals.items() if math.isfinite(v)}
    return min(finite, key=finite.get) if finite else ""


def _bold_best(results: dict, setting: str, key: str, text: str, alg: str) -> str:
    return f"**{text}**" if alg == best_alg(results, setting, key) else text


def comparison_table(results: dict, settings, paper: dict | None = None, spread: bool = False) -> str:
    """Settings x metrics rows, algorithms as columns; ours (paper's)."""
    algs = list(results)
    rows = []
    for st in settings:
        for i, key in enumerate(METRICS):
            cells = []
            for a in algs:
                ours = pm(results[a][st], key) if spread else num(results[a][st][key])
                ours = _bold_best(results, st, key, ours, a)
                if paper is not None:
                    ours += f" ({num(paper[st][key].get(a))})"
                cells.append(ours)
            rows.append([comm_name(st) if i == 0 else "", METRIC_NAMES[key]] + cells)
    return table(["Comm.", "Metric"] + [_label(a) for a in algs], rows)


def sweep_table(sweep: dict, key: str, topo: dict) -> str:
    algs = list(sweep)
    labels = list(next(iter(sweep.values())))
    rows = [[lab, num(topo[lab]["observed"]), num(topo[lab]["mean_degree"])]
            + [_bold_best(sweep, lab, key, num(sweep[a][lab][key]), a) for a in algs] for lab in labels]
    return table(["range", "nbhd observed", "mean degree"] + [LABELS.get(a, a) for a in algs], rows)


def not_best(results: dict, what: str, skip=()) -> list[list[str]]:
    """Table rows for the settings where the paper's method (``OURS``) is
    not the lowest in some metric: per metric its label, or "<best> <value>
    (<its label> <value>)"."""
    out = []
    for st in next(iter(results.values())):
        if st in skip:
            continue
        cells = []
        for key in METRICS:
            b = best_alg(results, st, key, among=PAPER_ALGS)
            lost = b and b != OURS and results[b][st][key] < results[OURS][st][key]
            cells.append(f"{LABELS[b]} {num(results[b][st][key])} ({LABELS[OURS]} {num(results[OURS][st][key])})"
                         if lost else LABELS[OURS])
        if any(c != LABELS[OURS] for c in cells):
            out.append([what, comm_name(st)] + cells)
    return out


def fig(path: str, caption: str) -> str:
    return f"![{caption}]({path})\n\n*{caption}*\n"


def _git_state() -> str:
    """The commit of the checkout holding this package (wherever the command
    runs), and its package files with uncommitted changes."""
    commit = provenance.git_commit()
    if not commit:
        return "outside a git checkout"
    root = Path(__file__).resolve().parents[2]
    try:
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        status = ""
    dirty = [l[3:] for l in status.splitlines() if l[3:].startswith("diskf_mesh/")]
    return f"commit {commit[:7]}" + (f", with uncommitted changes to {', '.join(dirty)}" if dirty else "")


# --------------------------------------------------------------------------
# sections
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class Context:
    res: studies.Results
    figdir: str = "figures"

    def f(self, name: str) -> str:
        return f"{self.figdir}/{name}"


def section_setup(ctx: Context) -> str:
    s1 = load_scenario(studies.STATIONARY)
    p = s1.params
    w = float(np.arctan2(s1.A[1, 0], s1.A[0, 0]))
    cfg = ctx.res.config
    rows = [
        ["rotation per tick ω", "not given", f"{w:.4f} rad (2π/{2 * np.pi / w:.0f}: one lap in {2 * np.pi / w:.0f} ticks)"],
        ["initial state x0", "not given", f"{s1.x0.tolist()}"],
        ["initial covariance P0", "not given", f"{s1.P0.tolist()} for every agent"],
        ["horizon", "not given", f"{cfg['steps'] or s1.steps} ticks"],
        ["G, Q, R, input d", "G=[1,1]ᵀ, Q=0.2 I, R=2, d=0 then 10 at k=10", "same"],
        ["observation window", "a hyper-parameter, value not given", f"{p.window} ticks, reset on a valid fused input: {p.reset}"],
        ["compensation gain M_i", "P̄, ε = 0.05", f"`{p.compensation}` (see `equations.compensation_gain`), ε = {p.eps}; Table I shows every form"],
        ["KCF consensus step", "not given", f"{p.consensus_eps}"],
        ["Scenario 2 geometry", "a sketch (Fig. 2)", "ours, documented in `scenarios/dynamic.toml`"],
        ["link rule", "\"when the communication ranges of two agents intersect\"",
         "distance ≤ range (the rule used here; \"ranges intersect\" could also mean ≤ 2·range)"],
        ["\"1-hop\" in Scenario 2 (Table I)", "not defined", f"the range-{studies.PAPER_RANGE:g} graph"],
        ["error metrics", "MAE, RMSE, not defined further",
         "Euclidean position error over agents, ticks, seeds; input error only where an agent has a fused input"],
        ["seeds", "20, averaged", f"{cfg['seeds']} (0..{cfg['seeds'] - 1}); spread = std of the per-seed metric"],
    ]
    return "## 1. Setup: what the paper gives and what we chose\n\n" + table(["item", "paper", "ours"], rows) + "\n"


def section_scenario2(ctx: Context) -> str:
    t = ctx.res.topology
    r = f"{studies.PAPER_RANGE:g}"
    rows = [[lab, num(v["mean_degree"]), num(v["isolated_share"]), f"{num(v['components_mean'])} [{v['components_min']}, {v['components_max']}]",
             v["changes"], num(v["observed"])] for lab, v in t.items()]
    return (
        "## 2. Scenario 2 (dynamic topology)\n\n"
        "Four static agents at (±100, ±100) and five mobile agents on closed loops (two opposite circles, two "
        "racetracks, a bow-tie); every agent measures x or y (alternating by id) while it shares the target's "
        "quadrant; a link exists while two agents are at most the range apart. The static agents are 200 apart, "
        f"so at range {r} only mobile agents connect them.\n\n"
        + fig(ctx.f("scenario_dynamic.png"), "Scenario 2: layout, paths and range circles, then the links at three ticks")
        + "\nHow connected the graph is at each range (one tick = one graph; `nbhd observed` is the share of "
        "agent-ticks whose 1-hop neighbourhood, the agent included, holds a measurement: the most a one-round "
        f"algorithm can use; `own` alone is {num(t['0']['own_observed'])}):\n\n"
        + table(["range", "mean degree", "isolated share", "components mean [min, max]", "graph changes", "nbhd observed"], rows)
        + "\n"
    )


def section_table_ii(ctx: Context) -> str:
    return (
        "## 3. Scenario 1 (the paper's Table II)\n\n"
        "Ours, with the paper's value in parentheses; bold is our lowest one-round estimator of the row.\n\n"
        + comparison_table(ctx.res.table_ii, ["all", "ring", "none"], paper_values.TABLE_II) + "\n\n"
        + references_note(ctx.res.table_ii) + "\n\n"
        + fig(ctx.f("scenario_stationary.png"), "Scenario 1: four static quadrant agents")
        + fig(ctx.f("inputs_stationary_ring.png"), "Scenario 1, 1-hop: input estimates per node (the paper's Fig. 7)")
        + fig(ctx.f("states_stationary_ring.png"), "Scenario 1, 1-hop: x and y against time per node (the paper's Figs. 8, 9)")
        + fig(ctx.f("trajectories_stationary_ring.png"), "Scenario 1, 1-hop: 2-D trajectories at node 1 (the paper's Fig. 10)")
    )


def references_note(t2: dict) -> str:
    """What Table II's two centralized columns are, with their numbers."""
    below = [LABELS[a] for a in FAMILY if a in t2 and t2[a]["all"]["mae_state"] < t2[BOUND]["all"]["mae_state"]]
    pr = t2.get(EXTENSION, {}).get("all", {}).get("mae_state")
    return (
        "The last two columns are references, not one-round estimators: one centre that receives every agent's "
        "measurement at every tick. They ignore the links, so each is the same in every block.\n\n"
        f"- **{_label(BOUND)}** (`engine/centralized.py`, `run_centralized`): the Gillijns–De Moor filter, an "
        "input estimate unbiased for every input sequence, then the state update. It is the optimum among "
        "input-unbiased estimators when the input is strongly detectable from the stacked sensors; it assumes "
        "nothing about the input, so it bounds only estimators that assume nothing either. An estimator with "
        "an input model can be below it"
        + (f" ({', '.join(below)} in all-to-all, MAE(state) {num(t2[BOUND]['all']['mae_state'])})." if below else ".")
        + f"\n- **{_label(PBOUND)}** (`run_centralized_persist`): the joint Kalman filter of the state and the "
        f"input with {LABELS[EXTENSION]}'s input model (a random walk at the scenario's scale): the optimum under "
        f"that model, and so the bound of {LABELS[EXTENSION]}"
        + (f" (all-to-all: {LABELS[EXTENSION]} {num(pr)}, this filter {num(t2[PBOUND]['all']['mae_state'])})."
           if pr is not None and PBOUND in t2 else ".")
    )


def section_dynamic(ctx: Context) -> str:
    r = f"{studies.PAPER_RANGE:g}"
    return (
        f"## 4. Scenario 2 at range {r} and all-to-all (the paper's Fig. 5)\n\n"
        "Mean ± std over seeds; bold is the lowest mean. The paper gives this only as a bar chart; its Table I "
        "has DISKF's values (section 6).\n\n"
        + comparison_table(ctx.res.dynamic, [r, "all"], spread=True) + "\n\n"
        + fig(ctx.f("dynamic_bars.png"), f"Scenario 2: MAE and RMSE at range {r} and all-to-all")
        + fig(ctx.f("trajectories_dynamic_120.png"), f"Scenario 2, range {r}: 2-D trajectories at node 1")
        + fig(ctx.f("inputs_dynamic_120.png"), f"Scenario 2, range {r}: input estimates per node")
        + fig(ctx.f("states_dynamic_120.png"), f"Scenario 2, range {r}: x and y against time at nodes 1, 5, 9")
    )


def section_sweep(ctx: Context) -> str:
    sw, t = ctx.res.sweep, ctx.res.topology
    return (
        "## 5. Error against communication range (the paper's Fig. 6)\n\n"
        "Range 0 is isolated agents; `all` is all-to-all (every range ≥ 283 is all-to-all in Scenario 2). "
        "Bold is the lowest of the row.\n\n**MAE(state)**\n\n" + sweep_table(sw, "mae_state", t)
        + "\n\n**MAE(input)**\n\n" + sweep_table(sw, "mae_input", t) + "\n\n"
        + fig(ctx.f("error_vs_range.png"), "Scenario 2: MAE of input and state against range (log scale)")
    )


def section_table_i(ctx: Context) -> str:
    comp = ctx.res.compensation
    default = load_scenario(studies.STATIONARY).params.compensation
    rows, checks = [], []
    for env, cells in comp.items():
        for comm, cell in cells.items():
            paper = paper_values.TABLE_I.get((env, comm), {})
            for form, row in cell["rows"].items():
                flag = "no" if form == "none" else "yes"
                pv = paper.get(flag, {})
                name = f"{form}" + (" (default)" if form == default else "") + (" = M_i as printed" if form == "paper" else "")
                rows.append([env, comm, name] + [f"{num(row[k])} ({num(pv.get(k))})" for k in
                                                  ("mae_input", "rmse_input", "mae_state", "rmse_state")])
            if cell["bit_identical"] is not None and comm == "all-to-all":
                checks.append(f"- {env}, all-to-all: estimates of all {len(cell['rows'])} forms bit-identical "
                              f"(x, P, d): **{'yes' if cell['bit_identical'] else 'NO'}**")
    return (
        "## 6. State compensation (the paper's Table I)\n\n"
        "DISKF with every gain form of eq. (compensation_state); `none` is the paper's \"No\" row, the paper's "
        "\"Yes\" value is shown beside every other form. Columns in the paper's order. Stationary 1-hop is the "
        f"ring, dynamic 1-hop the range-{studies.PAPER_RANGE:g} graph.\n\n"
        + table(["Env.", "Comm.", "gain form", "MAE(input)", "RMSE(input)", "MAE(state)", "RMSE(state)"], rows)
        + "\n\nIn all-to-all every agent fuses the same messages, so all predictions x̂ⱼ are equal and the "
        "compensation sum is exactly zero:\n\n" + "\n".join(checks) + "\n\n"
        "The paper's stationary 1-hop \"Yes\" row (15.76, 30.05, 4.67, 6.37) has input and state swapped "
        "with respect to its own Table II (state 15.76, input 4.67).\n"
    )


def section_window(ctx: Context) -> str:
    rows = []
    for env, cells in ctx.res.window.items():
        for comm, cell in cells.items():
            for name, row in cell["rows"].items():
                rows.append([env, comm, name] + [num(row[k]) for k in METRICS] + [num(row["input_coverage"])])
    return (
        "## 7. Observation time window (the paper's Fig. 3)\n\n"
        "DISKF without a window, with a window whose counter restarts only on the agent's own measurement, and "
        "with the paper's reset (the counter also restarts when input fusion had a valid input).\n\n"
        + table(["Env.", "Comm.", "variant"] + [METRIC_NAMES[k] for k in METRICS] + ["coverage"], rows) + "\n\n"
        + fig(ctx.f("window_stationary_ring.png"), "Scenario 1, 1-hop: the three window variants")
        + fig(ctx.f("window_dynamic_120.png"), f"Scenario 2, range {studies.PAPER_RANGE:g}: the three window variants")
    )


def _iso_rows(diag: dict) -> list:
    rows = []
    for scen in ("isolated_stationary", "isolated_dynamic"):
        d = diag[scen]
        for g, z in d["zero"].items():
            rows.append([scen.split("_")[1], g, f"{z:.3f}"] + [num(d[a][g]["mae_state"]) for a in d if a != "zero"])
    return rows


def section_diagnosis(ctx: Context) -> str:
    res = ctx.res
    r = f"{studies.PAPER_RANGE:g}"
    lost = (not_best(res.table_ii, "Scenario 1") + not_best(res.dynamic, "Scenario 2")
            + not_best(res.sweep, "Scenario 2 (sweep)", skip=(r, "all")))
    diag = res.diagnostics
    algs = [a for a in diag["isolated_dynamic"] if a != "zero"]
    var = diag["range_variants"]
    t = res.topology
    return (
        "## 8. Where DISKF is not the best, and why\n\n"
        + headline(res) + "\n\nEvery setting where some baseline is lower than DISKF in some metric "
        "(ties at two decimals are real differences in the third):\n\n"
        + (table(["scenario", "comm."] + [METRIC_NAMES[k] for k in METRICS], lost) if lost
           else "DISKF has the lowest value everywhere.") + "\n\n"
        "### 8.1 A sensor that sees one coordinate cannot separate the input from the state\n\n"
        "With a scalar measurement and a scalar input (HG = 1) the input estimate of eq. (input_estimation) is "
        "the whole innovation, d̂ = y − Hx̂, so after x* = x̂ + G d̂ that measurement leaves no innovation for "
        "the state: whatever the prediction got wrong is read as input and pushed into *both* coordinates "
        "through G = [1, 1]ᵀ. The error left unseen evolves as the zero dynamics x⁺ = (I − G(HG)⁻¹H)A x, whose "
        "non-zero eigenvalue (the invariant zero of (A, G, H)) is cos ω + sin ω for an x-sensor and cos ω − sin ω "
        "for a y-sensor. For any anticlockwise ω in (0, π/2) the x-sensor's zero is above 1: an agent that hears "
        "only x-measurements cannot keep an input-and-state estimate stable, whatever the filter. C-DRKF and "
        "L-DRKF, with no window, diverge; DISKF's window slows it down. KCF, which never feeds the input into "
        "its state, stays bounded. Isolated agents, mean state error by sensor type:\n\n"
        + table(["scenario", "sensor", "invariant zero"] + [LABELS[a] for a in algs], _iso_rows(diag))
        + "\n\n" + fig(ctx.f("isolated_by_sensor.png"), "Isolated agents in Scenario 2: x-sensors diverge, y-sensors do not")
        + "\nIn all-to-all (and at long range) neighbourhoods mix x- and y-sensors over a lap, the product of "
        "the zero dynamics contracts, and DISKF matches C-DRKF.\n\n"
        f"### 8.2 At range {r} most neighbourhoods see nothing, and DISKF only fuses what is measured now\n\n"
        f"At range {r} a neighbourhood holds a measurement in {num(t[r]['observed'] * 100, 0)} % of agent-ticks "
        f"(own: {num(t[r]['own_observed'] * 100, 0)} %): neighbours are close, so they sit in the same quadrant "
        "and see the target at the same time as the agent, or not at all. DISKF's state fusion (eqs. state_fusion, "
        "state_fusion_p) adds only the neighbours' *current* measurement information; a neighbour's better "
        "prior reaches the agent only through the small compensation step. DiffKF and KCF average the "
        "neighbours' priors every tick, so information travels several hops over time. And while no valid "
        "input is fused, DISKF predicts without any input (x* = x̂), so a blind agent drifts by G·d per tick, "
        "as the baselines do. DISKF variants at this range:\n\n"
        + table(["variant"] + [METRIC_NAMES[k] for k in METRICS],
                [[name] + [pm(row, k) for k in METRICS] for name, row in var.items()])
        + "\n\n" + variants_note(var) + " The last two rows move one mobile agent from an x- to a y-sensor "
        "(section 8.1).\n\n"
        "Below this range most agents are alone or in small groups (section 2), so section 8.1 dominates there. Where "
        "DISKF has the lowest MAE(state) but not the lowest RMSE(state), its errors have heavier tails than the "
        "baselines': the excursions of section 8.1 while an x-sensor group is on its own.\n"
        + window_note(res) + all_to_all_note(res) + hold_note(res)
    )


def variants_note(var: dict) -> str:
    """What the range-120 variants separate, read from their rows."""
    base, noin, diff = (var[k]["mae_state"] for k in ("DISKF", "DISKF, no input estimation", "DiffKF"))
    return (f"Without any input estimation DISKF's MAE(state) is {num(noin)} instead of {num(base)}: at this "
            "range the input estimates, formed from stale predictions, "
            + ("cost more state accuracy than they bring" if noin < base else "still help the state")
            + (f"; we attribute the rest of the gap to DiffKF ({num(diff)}) to the fusion of priors that DISKF "
               "does not do."
               if noin > diff else f", and without them DISKF is below DiffKF ({num(diff)})."))


def headline(res: studies.Results) -> str:
    """Which estimator is best at the paper's range, answered from the numbers."""
    r = f"{studies.PAPER_RANGE:g}"
    parts = []
    for key in ("mae_state", "mae_input"):
        b = best_alg(res.dynamic, r, key, among=PAPER_ALGS)
        v = res.dynamic[OURS][r][key]
        parts.append(f"{METRIC_NAMES[key]} {LABELS[OURS]} {num(v)}: " + (
            "the lowest of the paper's six" if b == OURS else f"not the lowest, {LABELS[b]} has {num(res.dynamic[b][r][key])}"))
    return f"At range {r}: " + "; ".join(parts) + "."


def window_note(res: studies.Results) -> str:
    """8.3: what the reset does in our runs, read from section 7's rows."""
    lines = []
    for env, cells in res.window.items():
        rows = cells["1-hop"]["rows"]
        names = list(rows)
        none_, noreset, reset = (rows[n]["mae_state"] for n in names)
        lines.append(f"{env.capitalize()} 1-hop: MAE(state) {num(none_)} without a window, {num(noreset)} with the window "
                     f"and no reset, {num(reset)} with the reset")
    return (
        "\n### 8.3 The window reset\n\n"
        "With the reset, any valid input from a neighbour restarts the counter. In the ring some neighbour "
        "nearly always measures, so the window then never blocks an estimate: the reset row equals the "
        "no-window row, whatever the window length. " + "; ".join(lines) + ". The paper reports the reset as "
        "an improvement (its Fig. 3b); where the no-reset row is lower above, our runs disagree: a neighbour's "
        "valid input says nothing about the coordinate this agent is about to measure after a gap.\n"
    )


def all_to_all_note(res: studies.Results) -> str:
    a = res.dynamic[OURS]["all"]["mae_state"]
    c = res.dynamic["cdrkf"]["all"]["mae_state"]
    return (
        "\n### 8.4 All-to-all in Scenario 2\n\n"
        f"DISKF {num(a)} against C-DRKF {num(c)} (MAE(state), {num(100 * (a - c) / c, 1)} %). In Scenario 1 one "
        "agent measures at a time and the two are equal; in Scenario 2 several agents can measure at once. "
        "C-DRKF then estimates the input once from the stacked measurements; DISKF fuses the agents' individual "
        "input estimates by covariance intersection, which is not that joint estimate (the individual "
        "estimates share the prediction error and CI does not model it). The paper's \"same as the central "
        "estimator\" holds for the state fusion given the fused input, not for the input fusion itself.\n"
    )


def hold_note(res: studies.Results) -> str:
    """8.5: the hold_input extension in every setting, from its rows."""
    rows = []
    for env, cells in res.hold.items():
        for comm, cell in cells.items():
            for name, row in cell["rows"].items():
                rows.append([env, comm, name] + [num(row[k]) for k in METRICS])
    return (
        "\n### 8.5 An extension: hold the last fused input (off by default)\n\n"
        "When no agent in the neighbourhood has an input estimate, the paper's DISKF predicts with no input "
        "(x̂* = x̂), although the input here is a lasting step. `hold_input = true` in a scenario's "
        "`[estimator]` table (or `Params(hold_input=True)`) predicts with the last fused input instead. It is "
        "not in the paper, so the default stays off and every other table uses the paper's rule.\n\n"
        + table(["Env.", "Comm.", "variant"] + [METRIC_NAMES[k] for k in METRICS], rows) + "\n\n"
        "Holding helps wherever neighbours sometimes bring a good input estimate (1-hop in both scenarios), "
        "and hurts isolated agents: there the held value is the agent's own estimate, which for an x-sensor is "
        "the unstable one of section 8.1, and holding it carries the error through the whole unobserved gap.\n"
    )


# --------------------------------------------------------------------------
# beyond the paper
# --------------------------------------------------------------------------
ONE_ROUND = estimators.NAMES  # every estimator: one exchange round per tick is the interface
NEES_BAND = (1.6, 2.5)  # the 95 % band of the averaged NEES for n = 2


def family_check(rows: dict, key: str) -> tuple:
    """(best of the family, best other one-round (name, value), within 1 %)."""
    fam = min(rows[a][key] for a in rows if a in FAMILY)
    others = {a: rows[a][key] for a in rows if a in ONE_ROUND and a not in FAMILY and math.isfinite(rows[a][key])}
    b = min(others, key=others.get)
    return fam, (b, others[b]), fam <= 1.01 * others[b]


def overview_table(ov: dict, key: str) -> str:
    rows = []
    for st, r in ov.items():
        fam, (b, bv), ok = family_check(r, key)
        rows.append([st, num(r[OURS][key]), num(r[EXTENSION][key]), f"{_label(b)} {num(bv)}",
                     num(r[BOUND][key]), num(r[PBOUND][key]),
                     "yes" if ok else f"**no** ({num(100 * (fam - bv) / bv, 1)} % above)"])
    return table(["setting", LABELS[OURS], LABELS[EXTENSION], "best other one-round", "Centralized (bound)",
                  "Centralized, persistent input", "DISKF family lowest (or within 1 %)"], rows)


def nees_table(ov: dict, key: str) -> str:
    algs = [a for a in next(iter(ov.values()))]
    rows = [[st] + [num(r[a][key]) for a in algs] for st, r in ov.items()]
    return table(["setting"] + [_label(a) for a in algs], rows)


def ablation_table(abl: dict) -> str:
    cells = [(env, comm) for env, cs in abl.items() for comm in cs]
    names = list(abl[cells[0][0]][cells[0][1]]["rows"])
    rows = []
    for name in names:
        row = [name]
        for env, comm in cells:
            r = abl[env][comm]["rows"][name]
            row.append("diverged" if r.get("diverged") else
                       f"{num(r['mae_state'])} / {num(r['mae_input'])} / {num(r['nees_observed'], 1)}")
        rows.append(row)
    return table(["variant"] + [f"{env} {comm}" for env, comm in cells], rows)


def robustness_table(rb: dict) -> str:
    algs = list(next(iter(rb.values())))
    rows = []
    for st, r in rb.items():
        fam, (b, bv), ok = family_check(r, "mae_state")
        fam_i, (bi, biv), ok_i = family_check(r, "mae_input")
        rows.append([st] + [num(r[a]["mae_state"]) for a in algs]
                    + [num(r[EXTENSION]["mae_input"]), num(r[EXTENSION]["nees_observed"], 1),
                       ("yes" if ok else "**no**") + " / " + ("yes" if ok_i else "**no**")])
    return table(["setting / perturbation"] + [f"{_label(a)} MAE(state)" for a in algs]
                 + ["DISKF-R MAE(input)", "DISKF-R NEES observed", "family lowest: state / input"], rows)


def robust_targets(res: studies.Results) -> list:
    """The robust variant's targets, each with its measured numbers and met or not."""
    ov = res.overview
    def cell(st):
        return ov[st]
    r120, ring = cell("Scenario 2 / range 120"), cell("Scenario 1 / 1-hop (ring)")
    lows = [(st, key) for st, r in ov.items() for key in ("mae_state", "mae_input") if not family_check(r, key)[2]]
    out = [["DISKF family lowest MAE(state) and MAE(input) of the one-round estimators (or within 1 %), every setting",
            "met" if not lows else "not met in " + ", ".join(f"{st} ({METRIC_NAMES[k]})" for st, k in lows)]]
    out.append(["Scenario 2 range 120: MAE(state) ≤ 20", f"{num(r120[EXTENSION]['mae_state'])}: "
                + ("met" if r120[EXTENSION]["mae_state"] <= 20 else "not met")])
    out.append(["Scenario 1 ring: MAE(state) ≤ 5", f"{num(ring[EXTENSION]['mae_state'])}: "
                + ("met" if ring[EXTENSION]["mae_state"] <= 5 else "not met")])
    for st in ("Scenario 1 / all-to-all", "Scenario 2 / all-to-all"):
        r = cell(st)
        v, c, cp = r[EXTENSION]["mae_state"], r[BOUND]["mae_state"], r[PBOUND]["mae_state"]
        out.append([f"{st}: MAE(state) within 1 % of the centralized bound",
                    f"{num(v)} against {num(c)}: " + ("met" if v <= 1.01 * c else "not met")
                    + (" (below it: DISKF-R's input model)" if v < c else "")
                    + f"; against the centralized filter of the same model {num(cp)}: "
                    + ("met" if v <= 1.01 * cp else "not met")])
        nees = r[EXTENSION]["nees"]
        out.append([f"{st}: DISKF-R mean NEES inside [{NEES_BAND[0]}, {NEES_BAND[1]}]",
                    f"{num(nees)}: " + ("met" if NEES_BAND[0] <= nees <= NEES_BAND[1] else "not met")])
    high = [(st, r[EXTENSION]["nees_observed"]) for st, r in ov.items() if not r[EXTENSION]["nees_observed"] <= 4.0]
    out.append(["DISKF-R mean NEES ≤ 2n = 4 over the agent-ticks whose neighbourhood measures, every setting",
                "met" if not high else "not met in " + ", ".join(f"{st} ({num(v, 1)})" for st, v in high)])
    rb = res.robustness
    if rb:
        lows = [(st, key) for st, r in rb.items() for key in ("mae_state", "mae_input") if not family_check(r, key)[2]]
        out.append(["Robustness (10.5, 40 unseen seeds): DISKF family lowest MAE(state) and MAE(input)",
                    "met" if not lows else "not met in " + ", ".join(f"{st} ({METRIC_NAMES[k]})" for st, k in lows)])
        high = [(st, r[EXTENSION]["nees_observed"]) for st, r in rb.items() if not r[EXTENSION]["nees_observed"] <= 4.0]
        out.append(["Robustness (10.5): DISKF-R NEES ≤ 4 over observed agent-ticks",
                    "met" if not high else "not met in " + ", ".join(f"{st} ({num(v, 1)})" for st, v in high)])
    return out


def cfg_of(res: studies.Results) -> studies.StudyConfig:
    return studies.StudyConfig(seeds=res.config["seeds"], steps=res.config["steps"])


def section_robust(ctx: Context) -> str:
    res = ctx.res
    return (
        "## 10. Beyond the paper: robust DISKF (`diskf-r`) and the centralized bound\n\n"
        "`diskf` above is the paper's Algorithm 1. `diskf-r` (`diskf_mesh/estimators/diskf_robust.py`, switches in "
        "`model.RobustOptions`) is our extension under the paper's constraints: one exchange round per tick, the "
        "same message (x̂, P̂, x̃, P̃ and an input estimate with its covariance; no measurement, H or R), so the "
        "same 8(2n + 2n² + m + m²) bytes of floats, 161 bytes on the wire for n = 2, m = 1, whatever the "
        "neighbourhood's size. The derivations are in the module and in `core/equations.py`.\n\n"
        "**Why the paper's input estimate is not enough.** Gillijns–De Moor's estimate is unbiased for *any* "
        "input sequence. With one sensor type and one input it absorbs the whole innovation, and the error follows "
        "the zero dynamics of (A, G, H): an x-sensor's zero is cos ω + sin ω > 1 here (section 8), so no unbiased "
        "estimator is stable on it, and isolated agents or x-only neighbourhoods are in that case most of the time. "
        "An estimator can only do better by assuming something about the input.\n\n"
        "**What `diskf-r` assumes: the input persists** (`persist`): a random walk d_k = d_{k−1} + η, "
        "η ~ N(0, Q_d), Q_d = `input_walk`·I (default from the scenario's scales, √(q_process·q_sensor): 0.45 "
        "here, the input may change by about 0.7 per tick), starting from a wide prior N(0, `input_prior`·I) "
        "(default 10⁴·max(q_process, q_sensor) = 2·10⁴ here: nothing known; `input_models.default_scales`; "
        "`input_model` selects a mean-reverting input or none instead). Every agent runs the Kalman "
        "filter of the joint state (x_k, d_{k−1}) and keeps the cross-covariance cov(x̄, d̄) to itself. A constant "
        "input is observable through any sensor with H(I − A)⁻¹G ≠ 0, an x-sensor included, so an isolated agent "
        "learns the input while it measures and predicts with it, and with its covariance, while it does not. As "
        "Q_d → ∞ the model assumes nothing and the filter tends to Gillijns–De Moor's. Per tick, what a receiver "
        "does with the messages:\n\n"
        "1. **Own joint prior** (`equations.input_walk`): x̂ = A x̄ is the prediction of v_k = x_k − G d_{k−1} (it "
        "does not depend on the input); cov(v, d) = A C, cov(d) = S̄ + Q_d.\n"
        "2. **CI of the priors** (`prior_ci`): the neighbours' x̂_j fused by the paper's fast CI (consistent for "
        "any correlation) replace the own marginal of v, the conditional p(d | v) kept "
        "(`equations.replace_marginal`).\n"
        "3. **Relayed fused inputs** (`relay`): the message's (d, S) is the sender's last fused input (Algorithm 1 "
        "lists d̄, S̄ among the exchanged values); their fast CI (with S + Q_d) replaces the own marginal of d, "
        "p(v | d) kept. An agent that never measured learns the input from a neighbour.\n"
        "4. **The input's covariance in the prediction** (`inject`, `equations.input_to_state`): x* = v + G d, "
        "P* = P_v + G Bᵀ + B Gᵀ + G S Gᵀ (B = cov(v, d)). The paper's eq. (info_kf_prediction) keeps the mean and "
        "drops the covariance terms (P̂* = P̂): that is why DISKF's NEES is large.\n"
        "5. **The measurement**: the neighbourhood's stacked information Σ P̃ⱼ⁻¹ − P̂ⱼ⁻¹ = Σ HⱼᵀRⱼ⁻¹Hⱼ (exact from "
        "the messages) added in information form; the measurement is of x only, so the input's update is "
        "`replace_marginal` of x: together the exact joint Kalman update of (x, d).\n\n"
        "It is exact where a neighbourhood is one agent (the agent's own joint filter) and in all-to-all: every CI "
        "returns the common prediction and input and `diskf-r` *is* the centralized filter with the same model "
        "(`tests/test_robust.py`, to 1e-9). In between, steps 2 and 3 keep the agent's own correlation between v "
        "and d for a fused prior whose correlation is unknown, an approximation whose NEES is measured below. "
        "Switches off by default, each an ablation row: `unbiased` (the exact Gillijns–De Moor update where the "
        "heard sensors make the input strongly detectable, `gate` and `latch`: rank(HG) = m and every invariant "
        "zero of (A, G, H_N) inside the unit circle, `equations.strongly_detectable`), `inflate` (a fading factor, "
        "`equations.innovation_scale`), and the paper's `compensate` and `window` (the window never closes "
        "under `persist`: the input is held from the first measurement on, and the reset keeps it open). The "
        "first `diskf-r` of this project (gated unbiased update, input assumed and not learned, fading factor) "
        "is the row \"first diskf-r\".\n\n"
        "The **centralized bound** (`diskf_mesh/engine/centralized.py`) is one centre with every agent's "
        "measurement at every tick running the exact Gillijns–De Moor recursion: no one-round method sees more, "
        "and it assumes nothing about the input. It is in every table of this report as a reference row (never "
        "bold, never \"best\"). Because `diskf-r` assumes the input persists, it can be, and in most settings is, "
        "*below* that bound; its own bound is the **centralized filter with the same persistent-input model** "
        "(`run_centralized_persist`), the second reference row of the tables in this section.\n\n"
        "### 10.1 The targets, measured\n\n"
        + table(["target", "measured"], robust_targets(res)) + "\n\n"
        "### 10.2 Every setting: the DISKF family against every one-round estimator and the bounds\n\n"
        "**MAE(state)**\n\n" + overview_table(res.overview, "mae_state") + "\n\n"
        "**MAE(input)**\n\n" + overview_table(res.overview, "mae_input") + "\n\n"
        + fig(ctx.f("error_vs_range.png"), "Scenario 2: MAE against range, with DISKF-R and the centralized bound")
        + "\n### 10.3 Consistency: NEES of every estimator\n\n"
        f"n = 2; a consistent filter has mean NEES 2 (95 % band of the averaged NEES about [{NEES_BAND[0]}, "
        f"{NEES_BAND[1]}]). Mean over all agent-ticks and seeds:\n\n" + nees_table(res.overview, "nees")
        + "\n\nMean over the agent-ticks whose neighbourhood (the agent included) holds a measurement:\n\n"
        + nees_table(res.overview, "nees_observed") + "\n\n"
        "### 10.4 Ablation: each ingredient switched\n\n"
        "Each cell: MAE(state) / MAE(input) / NEES over observed agent-ticks; 20 seeds. The `input_walk` and "
        "`input_prior` rows are the sensitivity of the one assumption.\n\n"
        + ablation_table(res.robust_ablation) + "\n\n"
        "### 10.5 Robustness: other speeds, both directions, a wide prior, other inputs, unseen seeds\n\n"
        f"Seeds {studies.robust_seeds(cfg_of(res)).start}..{studies.robust_seeds(cfg_of(res)).stop - 1} (no other "
        "study uses them); the defaults of every estimator unchanged. ω₀ = 2π/40 is the shipped turn rate; "
        "clockwise turns make the y-sensors the ones with the unstable invariant zero. The last two perturbations "
        "change the input itself, the thing `diskf-r` makes an assumption about.\n\n"
        + robustness_table(res.robustness) + "\n\n"
        "### 10.6 Which to use\n\n"
        "- `diskf` reproduces the paper; use it to compare with the paper's numbers.\n"
        "- `diskf-r` for a real network whose unknown input changes slowly or in occasional steps: the lowest "
        "error of the one-round estimators in every setting of 10.2 and 10.5 unless marked there, and a calibrated "
        "covariance (10.3). Its assumption is stated and its sensitivity measured (10.4). Its engine CPU per tick is "
        "about 1.7 times DISKF's (Table II batch, measured side by side: 0.68 s against 0.40 s).\n"
        "- Where the input may jump arbitrarily every tick, `unbiased = true` uses the assumption-free update "
        "wherever the heard sensors allow it.\n"
        "- The centralized filters are the yardsticks: how far a one-round method is from the optimum of its model.\n"
    )


def section_differences(ctx: Context) -> str:
    return (
        "## 9. Differences from the paper, in short\n\n"
        "- Constants the paper omits (ω, x0, P0, horizon, window length, KCF step, Scenario 2 geometry) are ours, "
        "section 1; the paper's absolute numbers depend on them, so only orderings and trends compare.\n"
        "- The compensation gain: the default is not the printed M_i = P̄ (section 6 shows all forms).\n"
        "- Link rule: distance ≤ range; \"ranges intersect\" would double the effective range.\n"
        "- Metrics: the paper does not define them; ours are Euclidean position error and input error where an "
        "estimate exists (coverage in section 7).\n"
        "- Table I's stationary 1-hop row is inconsistent with Table II in the paper itself (section 6).\n"
        "- Sections 8.1–8.4 explain every cell where DISKF is not the lowest; 8.5 shows an optional extension "
        "(hold the last fused input) that is not in the paper.\n"
    )


# --------------------------------------------------------------------------
# the held-out suite
# --------------------------------------------------------------------------
HELDOUT_COMMAND = "diskf-mesh report --heldout --out docs"


def _input_of(label: str) -> str:
    """The input of a held-out case, from its label ("S1 ring, zero": "zero")."""
    return label.rsplit(", ", 1)[-1]


def _count(items) -> str:
    """"a (3), b (2)": the items by how often they occur, most first."""
    return ", ".join(f"{k} ({v})" for k, v in Counter(items).most_common())


def where_right(doc: dict) -> list[str]:
    """One plain statement per estimator, from the held-out results: in how
    many cases it has the lowest state MAE and with which inputs and case
    groups, within 10 % of the lowest, more than twice it, diverged."""
    res = doc["results"]
    names = list(res[0]["rows"]) if res else []
    n = len(res)
    out = []
    for a in names:
        best, near, far, div, gone = [], 0, [], 0, 0
        for r in res:
            rows = r["rows"]
            if rows[a]["diverged"]:
                div += 1
                continue
            gone += heldout.lost(rows[a])
            lo = heldout.lowest(rows)
            v = rows[a]["mae_state"]
            if v == lo:
                best.append(r)
            if v <= 1.10 * lo:
                near += 1
            elif v > 2 * lo:
                far.append(r["case"])
        text = (f"- **{estimators.label(a)}**: the lowest state MAE in {len(best)} of {n} cases"
                + (f" (inputs: {_count(_input_of(r['case']) for r in best)}; groups: {_count(r['group'] for r in best)})"
                   if best else "")
                + f"; within 10 % of the lowest in {near}; more than twice the lowest in {len(far)}"
                + (f" ({'; '.join(far[:6])}{'; …' if len(far) > 6 else ''})" if far else "")
                + (f"; its covariance diverged in {div}" if div else "")
                + (f"; it lost the target in {gone} (its error beyond {heldout.FAR:g} × the target’s farthest "
                   "distance from the origin)" if gone else "") + ".")
        out.append(text)
    return out


def section_heldout(ctx: Context, doc: dict | None) -> str:
    head = (
        "## 11. Beyond the shipped cases: the held-out suite and DISKF-auto's choice\n\n"
        "`diskf-auto` runs a bank of input models (no input, random walks, zero-mean and mean-reverting inputs, "
        "oscillating inputs) and mixes them by their evidence; the figure shows its model probabilities over time "
        "for agent 1 of Scenario 1 in a ring, with three inputs (drawn by this run; `diskf_mesh.studies.heldout.choice_figure`).\n\n"
        + fig(ctx.f("auto_choice.png"), "DISKF-auto: probability of each input-model family over time (agent 1, "
              "Scenario 1 ring, seed 0), over the true input")
        + "\nThe held-out suite (`diskf_mesh/studies/heldout.py`, cases listed there) runs every estimator on "
        "inputs, models and networks no default was chosen on: every `[input]` kind on both shipped scenarios "
        "in every topology above, a constant-velocity model (n = 4) with a small 2-D acceleration input, a "
        "3-D state, p_i = 2 and mixed sensors, other turn rates, R × 0.01 and × 100, random geometric networks "
        "of 25 and 50 agents.\n\n"
    )
    if doc is None:
        return head + (f"Not run by this report: `{HELDOUT_COMMAND}` runs it; this section then holds every "
                       "case × every estimator and says when and from which commit it was made.\n")
    prov = doc.get(provenance.KEY) or {}
    commit = (prov.get("git_commit") or "no git checkout")[:7]
    made = (f"Made by `{' '.join(prov.get('command') or [HELDOUT_COMMAND])}`, started {prov.get('started', '?')} "
            f"from commit {commit}: {doc['seeds']} seeds; its {len(doc['results'])} cases took "
            f"{doc.get('cpu_seconds', 0):.0f} s of CPU in {doc.get('processes', 1)} processes. A `diskf-mesh report` "
            "without `--heldout` keeps this section as it was, so the sections above may be newer.")
    body = heldout.markdown(doc, header=False)
    return (head + "### 11.1 Where each estimator is the right one\n\n" + made + "\n\n"
            + "\n".join(where_right(doc)) + "\n\n### 11.2 Every case × every estimator\n\n"
            "Bold: the lowest state MAE of the case. NEES: the mean over the (tick, agent) cells whose "
            "neighbourhood measures / the share of the cells, where every seed's neighbourhood measures, whose "
            "NEES averaged over the seeds lies in the χ² 95 % band of that average.\n\n"
            + body.replace("### ", "#### ") + "\n")


def render(res: studies.Results, figdir: str = "figures", heldout_doc: dict | None = None,
           started: str | None = None) -> str:
    """The markdown report; ``heldout_doc``: the held-out suite's results with
    their provenance (section 11), ``started``: when the run began."""
    ctx = Context(res, figdir)
    cfg = res.config
    steps = cfg["steps"] or f"{load_scenario(studies.STATIONARY).steps} (the scenarios' default)"
    head = (
        "# Reproduction of the DISKF paper's experiments\n\n"
        f"Sections 1–10 and every figure: generated by `diskf-mesh report` ({cfg['seeds']} seeds, {steps} ticks) "
        f"from {_git_state()}" + (f", started {started}" if started else "") + ". "
        "Regenerate with `diskf-mesh report --out docs`, section 11's held-out suite too with "
        f"`{HELDOUT_COMMAND}` (their times: [performance](performance.md)); the figures alone with "
        "`diskf-mesh figures --out DIR`. The raw numbers are in `results.json` beside this file.\n"
    )
    parts = [head, section_setup(ctx), section_scenario2(ctx), section_table_ii(ctx), section_dynamic(ctx),
             section_sweep(ctx), section_table_i(ctx), section_window(ctx), section_diagnosis(ctx),
             section_differences(ctx), section_robust(ctx), section_heldout(ctx, heldout_doc)]
    return "\n".join(parts)


FRONT_COLUMNS = ("diskf", "diskf-r", "diskf-auto", "cdrkf", "ldrkf", "kcf", "diffkf", "gdkf")
FRONT_REFERENCES = {BOUND: "Centralized (bound)", PBOUND: "Centralized, persistent input"}


def front_page_table(table_ii: dict) -> str:
    """The README's Table II from ``results.json``'s ``table_ii``: ours (the
    paper's) per cell, the lowest one-round estimator of each row in bold,
    the centralized references last."""
    cols = [c for c in FRONT_COLUMNS if c in table_ii]
    mets = (("mae_state", "MAE(state)"), ("rmse_state", "RMSE(state)"), ("mae_input", "MAE(input)"),
            ("rmse_input", "RMSE(input)"))
    label = {**LABELS, "diskf-r": f"{LABELS.get('diskf-r', 'DISKF-R')} (ours)",
             "diskf-auto": f"{LABELS.get('diskf-auto', 'DISKF-auto')} (ours)"}
    refs = [r for r in REFERENCES if r in table_ii]
    lines = ["| Comm. | Metric | " + " | ".join(label.get(c, c) for c in cols) + " | "
             + " | ".join(FRONT_REFERENCES[r] for r in refs) + " |",
             "|---|---|" + "---|" * (len(cols) + len(refs))]
    for st, comm in (("all", "all-to-all"), ("ring", "1-hop (ring)"), ("none", "none")):
        for i, (key, name) in enumerate(mets):
            vals = {c: table_ii[c][st][key] for c in cols}
            best = min(round(v, 2) for v in vals.values() if v is not None and math.isfinite(v))
            cells = []
            for c in cols:
                v = vals[c]
                text = "-" if v is None or not math.isfinite(v) else f"{v:.2f}"
                if text != "-" and round(v, 2) == best:
                    text = f"**{text}**"
                if c in paper_values.COLUMNS:
                    text += f" ({paper_values.TABLE_II[st][key][c]:.2f})"
                cells.append(text)
            bounds = " | ".join(f"{table_ii[r][st][key]:.2f}" for r in refs)
            lines.append(f"| {comm if i == 0 else ''} | {name} | " + " | ".join(cells) + f" | {bounds} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------
# running: the studies as jobs, each engine run once
# --------------------------------------------------------------------------
def _scenario1(cfg: studies.StudyConfig, out) -> tuple:
    runs = studies.setting_runs(cfg, studies.STATIONARY, studies.PAPER_SETTINGS_1, keep=("ring",))
    paths = figures.stationary_figures(figures.Run(figures.RING_TITLE, *runs.runs["ring"]), out)
    return ({"table_ii": studies.paper_rows(runs, references=studies.TABLE_II_REFERENCES),
             "overview 1": runs.rows}, paths)


def _scenario2(cfg: studies.StudyConfig, out) -> tuple:
    r = f"{studies.PAPER_RANGE:g}"
    runs = studies.setting_runs(cfg, studies.DYNAMIC, studies.sweep_settings(), keep=(r,))
    sweep, dyn = studies.paper_rows(runs), studies.paper_rows(runs, [r, "all"])
    paths = figures.dynamic_figures(figures.Run(figures.DYNAMIC_TITLE, *runs.runs[r]), sweep, dyn, out)
    return {"sweep": sweep, "dynamic": dyn, "overview 2": runs.rows}, paths


def _random_geometric(cfg: studies.StudyConfig, out) -> tuple:
    runs = studies.setting_runs(cfg, studies.RANDOM_GEOMETRIC, [studies.RANDOM_GEOMETRIC_SETTING])
    return {"overview 3": runs.rows}, []


def _window(cfg: studies.StudyConfig, out) -> tuple:
    runs: dict = {}
    done = studies.window_ablation(cfg, runs=runs)
    ring, dyn = (figures.Run(title, *runs[cell]) for title, cell in
                 ((figures.WINDOW_RING_TITLE, ("stationary", "1-hop")), (figures.DYNAMIC_TITLE, ("dynamic", "1-hop"))))
    return {"window": done}, figures.window_figures(ring, dyn, out)


def _diagnostics(cfg: studies.StudyConfig, out) -> tuple:
    runs: list = []
    done = studies.diagnostics(cfg, runs=runs)
    return {"diagnostics": done}, figures.isolated_figure(figures.Run(figures.ISOLATED_TITLE, *runs[0]), out)


def _auto_choice(cfg: studies.StudyConfig, out) -> tuple:
    path = out / "auto_choice"
    heldout.choice_figure(path)
    return {}, [path]


def _study(field: str, fn):
    return lambda cfg, out: ({field: fn(cfg)}, [])


# (key, what its progress line calls it, the job); longest first, so that a pool ends with the short ones.
# Every estimator runs once per setting: the paper's tables, the overview (10.2) and the figures read the
# same runs.
JOBS = (
    ("scenario 2", "Scenario 2 at every range: Figs. 5 and 6, 10.2, and its figures", _scenario2),
    ("random-geometric", "random-geometric network (10.2)", _random_geometric),
    ("robustness", "robustness (10.5)", _study("robustness", studies.robustness)),
    ("robust ablation", "DISKF-R ablation (10.4)", _study("robust_ablation", studies.robust_ablation)),
    ("scenario 1", "Scenario 1: Table II, 10.2, and its figures", _scenario1),
    ("hold", "holding the input (8.5)", _study("hold", studies.hold_ablation)),
    ("compensation", "Table I: compensation", _study("compensation", studies.compensation_ablation)),
    ("window", "Fig. 3: window, and its figures", _window),
    ("diagnostics", "diagnostics (8), and the isolated agents' figure", _diagnostics),
    ("topology", "topology statistics", _study("topology", studies.topology_stats)),
    ("auto choice", "DISKF-auto's choice over time (figure, 11)", _auto_choice),
)


def run_job(key: str, cfg: studies.StudyConfig, figdir) -> tuple:
    """(results, figure paths, seconds) of the job ``key``: one task of ``run_jobs``."""
    t0 = time.monotonic()
    fn = dict((k, f) for k, _, f in JOBS)[key]
    parts, paths = fn(cfg, figures._Folder(figdir))
    return parts, paths, time.monotonic() - t0


def workers() -> int:
    """Processes for the jobs: the cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def run_heldout_case(case, seeds: int, steps: int | None) -> tuple:
    """(the held-out suite's record of ``case``, seconds, CPU seconds): one task of ``run_jobs``."""
    t0, c0 = time.monotonic(), time.process_time()
    record = heldout.case_record(case, seeds, steps)
    return record, time.monotonic() - t0, time.process_time() - c0


def run_jobs(cfg: studies.StudyConfig, figdir, progress=None, jobs: int = 1, cases=()) -> tuple:
    """Every job, and the held-out ``cases`` if given, in ``jobs`` processes
    (each seeded, so the numbers do not depend on which process runs it):
    (studies.Results, figure paths, [held-out record per case], CPU seconds of the cases);
    ``progress(title, seconds)`` after each job and each case. The jobs show
    no bars of their own (``progress`` says how far it is); Ctrl-C stops the
    workers at once (``pool.process_pool``)."""
    titles = {k: t for k, t, _ in JOBS}
    parts: dict = {}
    paths: dict = {}
    records: dict = {}
    size = Counter(c.group for c in cases)
    left = dict(size)
    cpu_seconds = 0.0

    def finished(key, part, figs, seconds):
        parts.update(part)
        paths[key] = figs
        if progress is not None:
            progress(titles[key], seconds)

    def case_done(i, record, seconds, cpu):
        nonlocal cpu_seconds
        records[i] = record
        cpu_seconds += cpu
        g = cases[i].group
        left[g] -= 1
        if progress is not None:
            progress(f"held-out suite, {g} {size[g] - left[g]}/{size[g]}: {cases[i].label}", seconds)

    # the largest held-out cases first, after the report's own jobs
    order = sorted(range(len(cases)), key=lambda i: -cases[i].scenario.N)
    quiet = replace(cfg, quiet=True, lines=False)
    if jobs <= 1:
        for key, _, _ in JOBS:
            finished(key, *run_job(key, quiet, figdir))
        for i in order:
            case_done(i, *run_heldout_case(cases[i], cfg.seeds, cfg.steps))
    else:
        import multiprocessing
        from concurrent.futures import as_completed

        with process_pool(jobs, multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(run_job, key, quiet, figdir): key for key, _, _ in JOBS}
            futures.update({pool.submit(run_heldout_case, cases[i], cfg.seeds, cfg.steps): i for i in order})
            for f in as_completed(futures):
                key = futures[f]
                if isinstance(key, int):
                    case_done(key, *f.result())
                else:
                    finished(key, *f.result())
    overview = studies.overview_rows(parts.pop("overview 1"), parts.pop("overview 2"), parts.pop("overview 3"))
    res = studies.Results(config={"seeds": cfg.seeds, "steps": cfg.steps, "algorithms": list(cfg.algorithms)},
                          overview=overview, **parts)
    return (res, [p for key, _, _ in JOBS for p in paths[key]], [records[i] for i in range(len(cases))],
            cpu_seconds)


def previous_heldout(path: Path) -> dict | None:
    """The held-out suite's results kept in an earlier ``results.json``
    (``heldout.REPORT_KEY``, with their own provenance; ``heldout.stored``),
    or None."""
    try:
        return heldout.stored(path)
    except heldout.Mismatch:
        return None


def write_report(cfg: studies.StudyConfig, out_dir, progress=None, jobs: int = 1,
                 with_heldout: bool = False) -> list[Path]:
    """Run every job (in ``jobs`` processes), which draw the figures from
    their own runs, then write the markdown and the JSON;
    ``progress(i, n, title, seconds)`` first with i = 0 (what runs, in how
    many processes), then after each job, each held-out case and the
    writing, if given. ``with_heldout`` also runs the
    held-out suite (section 11); without it, the suite's results of an
    earlier run in ``out_dir/results.json`` are kept, with their own
    provenance, and section 11 says when and how they were made."""
    out = Path(out_dir)
    started = provenance.now()
    cases = heldout.cases() if with_heldout else []
    n = len(JOBS) + len(cases) + 1
    steps = [0]
    if progress is not None:  # at once: the first study may take a minute
        progress(0, n, f"{len(JOBS)} studies" + (f" and {len(cases)} held-out cases" if cases else "")
                 + f" in {jobs} process{'es' if jobs > 1 else ''}", 0.0)

    def line(title: str, seconds: float) -> None:
        steps[0] += 1
        if progress is not None:
            progress(steps[0], n, title, seconds)

    kept = None if with_heldout else previous_heldout(out / "results.json")
    res, paths, records, cpu = run_jobs(cfg, out / "figures", line, jobs, cases)
    t0 = time.monotonic()
    scns = [load_scenario(studies.STATIONARY), load_scenario(studies.DYNAMIC)]
    doc = res.to_json()
    if with_heldout:
        kept = dict(heldout.document(records, cfg.seeds, cfg.steps), cpu_seconds=cpu, processes=jobs)
        kept[provenance.KEY] = provenance.record(
            scenario=[{"name": c.label, "sha256": provenance.content_hash(c.scenario)} for c in cases],
            seeds=cfg.seed_range, ticks=cfg.steps or max(c.scenario.steps for c in cases), estimator=cfg.algorithms,
            status="done", started=started)
    if kept is not None:
        doc[heldout.REPORT_KEY] = kept
    md = out / "reproduction.md"
    with atomic_open(md, "w") as f:
        f.write(render(res, "figures", kept, started))
    prov = provenance.record(scenario=scns, seeds=cfg.seed_range, ticks=cfg.steps or scns[0].steps,
                             estimator=cfg.algorithms, settings={s.name: s.params for s in scns}, status="done",
                             started=started)
    save_json(out / "results.json", provenance.attach(doc, prov), "out")
    line("reproduction.md and results.json", time.monotonic() - t0)
    return [md, out / "results.json", *paths]
