"""The report's figures: matplotlib PNGs, no pyplot (no global figure state).

Every ``plot_*`` function takes data already computed (traces, estimates,
study results) and writes one PNG; ``make_figures`` runs what they need and
writes them all. Figures are small (dpi 100) so they can live in git.

Every axis is labelled with its unit. The scenarios have no physical unit:
positions, ranges and errors are in one length unit (``LENGTH``), time in
ticks, and an input moves the target by G d per tick (``INPUT``). Legends
name the estimators by their labels (``label``), once per figure, above the
panels (``_legend``).
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from PIL import Image

from diskf_mesh.engine import batch as engine
from diskf_mesh.data import metrics
from diskf_mesh.studies import suite as studies
from diskf_mesh import estimators
from diskf_mesh.engine import centralized
from diskf_mesh.studies.experiment import LABELS
from diskf_mesh.data.outputs import atomic_open
from diskf_mesh.data.scenario import Scenario, simulate

DPI = 100
# each estimator's own colour (``Estimator.color``), and the centralized bound's
COLORS = {**{name: cls.color for name, cls in estimators.REGISTRY.items()}, centralized.NAME: "black"}
LENGTH = "length units"             # of positions, ranges and position errors
INPUT = "length units per tick"     # of the input d and its errors
TICK = "tick"
STATIC_COLOR, MOBILE_COLOR = "tab:red", "tab:green"
TRUTH_COLOR = "tab:olive"  # the truth: far from every estimator's colour (tests/test_figures.py checks it)
FORMATS = ("png", "pdf", "svg")


def label(alg: str) -> str:
    return LABELS.get(alg, alg)


def _figure(width: float, height: float, top: float = 0.86, hspace: float = 0.35, wspace: float = 0.35) -> Figure:
    """A figure with fixed margins: a layout engine or bbox_inches="tight"
    would draw every figure twice, which triples the time of a report."""
    pad = 0.75 / height  # three quarters of an inch for the tick labels and the axis label below
    return _margins(Figure(figsize=(width, height)), left=0.8 / width, right=1 - 0.2 / width, bottom=pad, top=top,
                    hspace=hspace, wspace=wspace)


def _margins(fig: Figure, **params) -> Figure:
    """``fig`` with these subplot parameters (matplotlib 3.11 ignores
    ``Figure(subplotpars=...)``; ``subplots_adjust`` is honoured)."""
    fig.subplots_adjust(**params)
    return fig


def _save(fig: Figure, path: Path) -> Path:
    """The figure in the format of ``path``'s suffix (``FORMATS``); a PNG at
    ``DPI``, reduced to a 256-colour palette (line plots lose nothing
    visible, the files shrink about threefold: they live in git)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() != ".png":
        with atomic_open(path, "wb") as f:
            fig.savefig(f, format=path.suffix[1:].lower(), dpi=DPI)
        return path
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    buf.seek(0)
    with Image.open(buf) as im:
        with atomic_open(path, "wb") as f:
            im.convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(f, format="PNG", optimize=True)
    return path


def _grid(n: int, cols: int, size=(3.6, 2.6), sharex=True, head: float = 0.6):
    """``n`` panels in rows of ``cols``, ``head`` inches above them for the
    title and the legend."""
    rows = -(-n // cols)
    height = size[1] * rows + head
    fig = _figure(size[0] * cols, height, top=1 - head / height)
    axes = fig.subplots(rows, cols, sharex=sharex, squeeze=False).ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    return fig, axes[:n]


def _legend(fig: Figure, axes, top: float | None = None, ncol: int | None = None) -> None:
    """One legend for the whole figure, centred just under the title: the
    labelled lines of every panel, each label once, in the order drawn."""
    handles = {}
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    y = fig.subplotpars.top + (1 - fig.subplotpars.top) * 0.5 if top is None else top
    fig.legend(handles.values(), handles.keys(), loc="center", bbox_to_anchor=(0.5, y),
               ncol=ncol or len(handles), fontsize=8, frameon=False)


def _label(ax, x: str | None = None, y: str | None = None) -> None:
    if x:
        ax.set_xlabel(x, fontsize=8)
    if y:
        ax.set_ylabel(y, fontsize=8)


def _limits(ax, truth: np.ndarray, margin: float = 0.35):
    """Axis limits from the truth, so a diverging estimate does not hide it."""
    lo, hi = np.nanmin(truth, axis=0), np.nanmax(truth, axis=0)
    pad = margin * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)


@dataclass(frozen=True)
class Run:
    """A simulated scenario setting and every algorithm's estimates on it."""

    title: str
    scn: Scenario
    trace: object
    ests: dict

    @classmethod
    def of(cls, cfg: studies.StudyConfig, name: str, setting, title: str, algs=None) -> "Run":
        """Every algorithm (or ``algs``) with the scenario's parameters."""
        scn = cfg.scenario(name, setting)
        tr = simulate(scn, cfg.seed_range)
        return cls(title, scn, tr, {a: engine.run(tr, a, scn.params) for a in (algs or cfg.algorithms)})

    @classmethod
    def variants(cls, cfg: studies.StudyConfig, name: str, setting, title: str, make_variants) -> "Run":
        """Estimates keyed by variant label, ``make_variants(params)``."""
        scn = cfg.scenario(name, setting)
        tr = simulate(scn, cfg.seed_range)
        _, ests = studies.run_variants(scn, make_variants(scn.params), cfg, trace=tr)
        return cls(title, scn, tr, ests)


# --------------------------------------------------------------------------
# the scenario
# --------------------------------------------------------------------------
def _quadrants(ax, extent: float):
    ax.axhline(0, color="0.6", lw=0.8)
    ax.axvline(0, color="0.6", lw=0.8)
    for sx, sy, q in ((1, 1, "Q1"), (-1, 1, "Q2"), (-1, -1, "Q3"), (1, -1, "Q4")):
        ax.text(sx * 0.92 * extent, sy * 0.92 * extent, q, ha="center", va="center", color="0.5")
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    _label(ax, f"x ({LENGTH})")


def _agents(ax, scn: Scenario, pos: np.ndarray, comm_range: float | None):
    for i, a in enumerate(scn.agents):
        c = MOBILE_COLOR if a.mobile else STATIC_COLOR
        ax.plot(*pos[i], "o" if a.mobile else "s", color=c, ms=7, zorder=4)
        ax.annotate(str(a.id), pos[i], xytext=(4, 4), textcoords="offset points", fontsize=8)
        if comm_range is not None and np.isfinite(comm_range):
            ax.add_patch(Circle(pos[i], comm_range, fill=False, ls=":", lw=0.7, color=c, alpha=0.7))


def plot_scenario(scn: Scenario, trace, path: Path, ticks=(1, 30, 60)) -> Path:
    """Layout with paths and the target, then the links at a few ticks."""
    pos = scn.positions(trace.positions.shape[0])
    extent = 1.15 * max(np.abs(pos).max(), np.abs(trace.truth_x[0]).max())
    fig = _figure(4.6 * (1 + len(ticks)), 4.8, top=0.86)
    axes = fig.subplots(1, 1 + len(ticks), squeeze=False)[0]
    ax = axes[0]
    _quadrants(ax, extent)
    ax.plot(*trace.truth_x[0].T, color="0.3", lw=0.8)
    for i, a in enumerate(scn.agents):
        if a.mobile:
            loop = np.vstack([a.path, a.path[:1]])
            ax.plot(*loop.T, "--", color=MOBILE_COLOR, lw=1)
    _agents(ax, scn, pos[0], None)
    for a, p in zip(scn.agents, pos[0]):
        if not a.mobile and np.isfinite(scn.comm_range):
            ax.add_patch(Circle(p, scn.comm_range, fill=False, ls=":", color=STATIC_COLOR))
    links = f"range circles {scn.comm_range:g}" if scn.topology == "range" else f"topology {scn.topology}"
    ax.set_title(f"{scn.name}: static (red), mobile paths (green),\ntarget seed 0 (gray); {links}", fontsize=10)
    _label(ax, None, f"y ({LENGTH})")
    L = np.broadcast_to(trace.links[0], (pos.shape[0],) + trace.links.shape[2:])
    for ax, k in zip(axes[1:], ticks):
        k = min(k, pos.shape[0])
        _quadrants(ax, extent)
        for i, j in zip(*np.nonzero(np.triu(L[k - 1], 1))):
            ax.plot(*pos[k - 1, [i, j]].T, color="tab:blue", lw=1.2)
        _agents(ax, scn, pos[k - 1], scn.comm_range)
        ax.plot(*trace.truth_x[0, k - 1], "*", color=TRUTH_COLOR, ms=10)
        ax.set_title(f"tick {k}: {int(np.triu(L[k - 1], 1).sum())} links, target *")
    return _save(fig, path)


# --------------------------------------------------------------------------
# estimates of one run
# --------------------------------------------------------------------------
def plot_trajectories(run: Run, path: Path, node: int = 0, seed: int = 0) -> Path:
    """2-D trajectory of every estimator at one node against the truth."""
    fig, axes = _grid(len(run.ests), 3, size=(3.6, 3.4), sharex=False, head=0.9)
    truth = run.trace.truth_x[seed]
    for ax, (alg, est) in zip(axes, run.ests.items()):
        ax.plot(*truth.T, color=TRUTH_COLOR, lw=1.5, label="truth")
        ax.plot(*est.x[seed, :, node].T, color=COLORS.get(alg), lw=1, label=label(alg))
        _limits(ax, truth)
        ax.set_aspect("equal")
        ax.set_title(label(alg), fontsize=9, color=COLORS.get(alg))
        _label(ax, f"x ({LENGTH})", f"y ({LENGTH})")
    _legend(fig, axes)
    fig.suptitle(f"{run.title}: trajectory estimated at node {run.scn.agents[node].id}, seed {seed}", y=0.985)
    return _save(fig, path)


def plot_inputs(run: Run, path: Path, seed: int = 0, ylim=(-20.0, 40.0)) -> Path:
    """Small multiples: one row per node, one column per estimator, the
    input estimate against time over the true input; gaps where the node
    has no input estimate."""
    N, algs = run.trace.shape[2], list(run.ests)
    width, height, head = 1.75 * len(algs) + 1.15, 0.95 * N + 1.5, 0.95
    fig = _margins(Figure(figsize=(width, height)), left=1.0 / width, right=1 - 0.1 / width,
                   bottom=0.5 / height, top=1 - head / height, hspace=0.12, wspace=0.08)
    axes = fig.subplots(N, len(algs), sharex=True, sharey=True, squeeze=False)
    t = np.arange(1, run.trace.shape[1] + 1)
    for c, alg in enumerate(algs):
        est = run.ests[alg]
        axes[0, c].set_title(label(alg), fontsize=9, color=COLORS.get(alg))
        for i in range(N):
            ax = axes[i, c]
            ax.axhline(0, color="0.85", lw=0.6)
            ax.plot(t, run.trace.truth_d[seed, :, 0], "--", color=TRUTH_COLOR, lw=0.8, label="true input")
            ax.plot(t, np.where(est.d_valid[seed, :, i], est.d[seed, :, i, 0], np.nan), color=COLORS.get(alg),
                    lw=0.9, label="estimate (gaps: none)")
            ax.tick_params(labelsize=7)
    axes[0, 0].set_ylim(*ylim)
    for i in range(N):
        axes[i, 0].set_ylabel(f"node {run.scn.agents[i].id}", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel(TICK, fontsize=8)
    fig.text(0.08 / width, 0.5, f"input estimate d ({INPUT}; axis clipped to {ylim[0]:g}..{ylim[1]:g})",
             rotation=90, va="center", ha="left", fontsize=8)
    _legend(fig, axes[:1, :1], top=1 - 0.45 / height)
    fig.suptitle(f"{run.title}: input estimate per node and estimator (seed {seed})", y=1 - 0.08 / height,
                 va="top", fontsize=11)
    return _save(fig, path)


def plot_states(run: Run, path: Path, nodes=None, seed: int = 0) -> Path:
    """x (top row) and y (bottom row) against time at the given nodes."""
    nodes = list(range(run.trace.shape[2])) if nodes is None else list(nodes)
    fig = _figure(3.6 * len(nodes) + 0.3, 6.0, top=0.85)
    axes = fig.subplots(2, len(nodes), sharex=True, squeeze=False)
    t = np.arange(1, run.trace.shape[1] + 1)
    truth = run.trace.truth_x[seed]
    for c, node in enumerate(nodes):
        for r, comp in enumerate("xy"):
            ax = axes[r, c]
            ax.plot(t, truth[:, r], color=TRUTH_COLOR, lw=1.5, label="truth")
            for alg, est in run.ests.items():
                ax.plot(t, est.x[seed, :, node, r], color=COLORS.get(alg), lw=0.9, label=label(alg))
            span = truth[:, r].max() - truth[:, r].min()
            ax.set_ylim(truth[:, r].min() - 0.5 * span, truth[:, r].max() + 0.5 * span)
            ax.set_title(f"node {run.scn.agents[node].id}: {comp}", fontsize=9)
            _label(ax, TICK if r == 1 else None, f"{comp} ({LENGTH})" if c == 0 else None)
    _legend(fig, axes)
    fig.suptitle(f"{run.title}: position estimates (seed {seed})", y=0.985)
    return _save(fig, path)


# --------------------------------------------------------------------------
# study results
# --------------------------------------------------------------------------
def _sweep_x(labels):
    """Numeric x for range labels, 'all' one step past the largest range."""
    nums = [float(s) for s in labels if s != "all"]
    step = (nums[-1] - nums[-2]) if len(nums) > 1 else 1.0
    return np.array([float(s) if s != "all" else nums[-1] + step for s in labels])


def plot_error_vs_range(sweep: dict, path: Path) -> Path:
    """MAE of input and state against communication range (Fig. 6)."""
    fig = _figure(11, 4.8, top=0.84)
    axes = fig.subplots(1, 2)
    labels = list(next(iter(sweep.values())))
    x = _sweep_x(labels)
    for ax, key, title in ((axes[0], "mae_input", f"input ({INPUT})"), (axes[1], "mae_state", f"position ({LENGTH})")):
        for alg, rows in sweep.items():
            y = np.array([rows[s][key] for s in labels])
            e = np.array([rows[s][f"{key}_std"] for s in labels])
            ax.errorbar(x, y, yerr=e, color=COLORS.get(alg), marker="o", ms=3, lw=1, capsize=2, label=label(alg))
        ax.set_yscale("log")
        ax.set_xticks(x, [s if s != "all" else "all" for s in labels], fontsize=8)
        _label(ax, f"communication range ({LENGTH}; 0 = isolated, all = all-to-all)", f"MAE of the {title}")
        ax.grid(alpha=0.3)
    _legend(fig, axes)
    fig.suptitle("Scenario 2: error against communication range (bars: std over seeds)", y=0.985)
    return _save(fig, path)


BAR_METRICS = ("mae_input", "rmse_input", "mae_state", "rmse_state")


def plot_bars(results: dict, path: Path, title: str) -> Path:
    """Grouped bars: per setting, MAE/RMSE of input and state for every
    algorithm, with the spread over seeds (the paper's Fig. 5)."""
    settings = list(next(iter(results.values())))
    fig = _figure(6.5 * len(settings), 4.8, top=0.8, wspace=0.15)
    axes = np.atleast_1d(fig.subplots(1, len(settings)))
    algs = list(results)
    w = 0.8 / len(algs)
    for ax, st in zip(axes, settings):
        for j, alg in enumerate(algs):
            xs = np.arange(len(BAR_METRICS)) + (j - (len(algs) - 1) / 2) * w
            ys = [results[alg][st][k] for k in BAR_METRICS]
            es = [results[alg][st][f"{k}_std"] for k in BAR_METRICS]
            ax.bar(xs, ys, w, yerr=es, color=COLORS.get(alg), label=label(alg), capsize=2)
        ax.set_xticks(np.arange(len(BAR_METRICS)), [k.replace("_", " ").upper() for k in BAR_METRICS], fontsize=8)
        ax.set_yscale("log")
        ax.set_title(f"range {st}" if st != "all" else "all-to-all", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    _label(axes[0], None, f"error (state: {LENGTH}; input: {INPUT})")
    _legend(fig, axes)
    fig.suptitle(title, y=0.985)
    return _save(fig, path)


def plot_window(run: Run, path: Path, node: int = 0, seed: int = 0) -> Path:
    """Fig. 3: input estimate at one node and state error (mean over agents
    and seeds) against time, one line per window variant in ``run.ests``."""
    fig = _figure(11, 4.6, top=0.76)
    ax_d, ax_x = fig.subplots(1, 2)
    tr = run.trace
    t = np.arange(1, tr.shape[1] + 1)
    ax_d.plot(t, tr.truth_d[seed, :, 0], "--", color=TRUTH_COLOR, lw=1.2, label="truth")
    # wide grey first, so a variant that coincides with "no window" stays visible on top of it
    styles = (("tab:gray", 3.0), ("tab:orange", 1.2), ("tab:blue", 1.0), ("tab:green", 1.0))
    for (name, est), (c, lw) in zip(run.ests.items(), styles):
        ax_d.plot(t, np.where(est.d_valid[seed, :, node], est.d[seed, :, node, 0], np.nan), color=c, lw=lw, label=name)
        e_state, _, _ = metrics.errors(tr, est)
        ax_x.plot(t, e_state.mean(axis=(0, 2)), color=c, lw=lw, label=name)
    ax_d.set_ylim(-30, 50)
    ax_d.set_title(f"DISKF input estimate, node {run.scn.agents[node].id}, seed {seed}", fontsize=10)
    ax_x.set_yscale("log")
    ax_x.set_title("DISKF position error, mean over agents and seeds", fontsize=10)
    _label(ax_d, TICK, f"input d ({INPUT})")
    _label(ax_x, TICK, f"position error ({LENGTH})")
    _legend(fig, (ax_d, ax_x))
    fig.suptitle(f"{run.title}: observation time window", y=0.985)
    return _save(fig, path)


def plot_sensor_split(run: Run, path: Path, zeros: dict) -> Path:
    """Isolated agents: mean state error against time by sensor type."""
    groups = studies.sensor_groups(run.scn)
    fig, axes = _grid(len(groups), len(groups), size=(5.2, 3.8), head=0.9)
    t = np.arange(1, run.trace.shape[1] + 1)
    for ax, (g, mask) in zip(axes, groups.items()):
        for alg, est in run.ests.items():
            e_state, _, _ = metrics.errors(run.trace, est)
            ax.plot(t, e_state[:, :, mask].mean(axis=(0, 2)), color=COLORS.get(alg), label=label(alg))
        ax.set_yscale("log")
        ax.set_title(f"agents measuring {g} (invariant zero {zeros[g]:.3f})", fontsize=9)
        ax.grid(alpha=0.3)
        _label(ax, TICK, f"position error ({LENGTH})")
    _legend(fig, axes)
    fig.suptitle(f"{run.title}: position error by sensor type, mean over agents and seeds", y=0.985)
    return _save(fig, path)


# --------------------------------------------------------------------------
# all of them
# --------------------------------------------------------------------------
class _Folder:
    """``folder / "name"`` is ``folder/name.<fmt>``: where each figure goes."""

    def __init__(self, folder, fmt: str = "png"):
        if fmt not in FORMATS:
            raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
        self.folder, self.fmt = Path(folder), fmt

    def __truediv__(self, name: str) -> Path:
        return self.folder / f"{name}.{self.fmt}"


def stationary_figures(ring: Run, out: _Folder) -> list[Path]:
    """Scenario 1 in a ring: the layout, and every estimator's trajectory,
    input and states (the paper's Figs. 7-10)."""
    return [plot_scenario(ring.scn, ring.trace, out / "scenario_stationary", ticks=()),
            plot_trajectories(ring, out / "trajectories_stationary_ring"),
            plot_inputs(ring, out / "inputs_stationary_ring"),
            plot_states(ring, out / "states_stationary_ring")]


def dynamic_figures(dynamic: Run, sweep: dict, dyn: dict, out: _Folder) -> list[Path]:
    """Scenario 2: the layout and links, every estimator at the paper's range
    (``dynamic``), error against range (``sweep``) and the bars of Fig. 5
    (``dyn``)."""
    return [plot_scenario(dynamic.scn, dynamic.trace, out / "scenario_dynamic"),
            plot_trajectories(dynamic, out / "trajectories_dynamic_120"),
            plot_inputs(dynamic, out / "inputs_dynamic_120"),
            plot_states(dynamic, out / "states_dynamic_120", nodes=(0, 4, 8)),
            plot_error_vs_range(sweep, out / "error_vs_range"),
            plot_bars(dyn, out / "dynamic_bars",
                      "Scenario 2: errors at range 120 and all-to-all (bars: std over seeds)")]


def isolated_figure(isolated: Run, out: _Folder) -> list[Path]:
    return [plot_sensor_split(isolated, out / "isolated_by_sensor", studies.sensor_zeros(isolated.scn))]


def window_figures(ring: Run, dynamic: Run, out: _Folder) -> list[Path]:
    """The window variants' input estimates, Scenario 1 ring and Scenario 2
    at the paper's range."""
    return [plot_window(ring, out / "window_stationary_ring"), plot_window(dynamic, out / "window_dynamic_120")]


RING_TITLE = "Scenario 1, 1-hop (ring)"
DYNAMIC_TITLE = f"Scenario 2, range {studies.PAPER_RANGE:g}"
ISOLATED_TITLE = "Scenario 2, isolated"
WINDOW_RING_TITLE = "Scenario 1, 1-hop"


def make_figures(cfg: studies.StudyConfig, out_dir, results: studies.Results | None = None,
                 fmt: str = "png") -> list[Path]:
    """Every figure into ``out_dir`` as ``fmt`` (``FORMATS``); studies not
    given in ``results`` are run."""
    out = _Folder(out_dir, fmt)
    sweep = results.sweep if results and results.sweep else studies.range_sweep(cfg)
    dyn = results.dynamic if results and results.dynamic else studies.dynamic_table(cfg)
    r120 = studies.range_setting(studies.PAPER_RANGE)
    ring = Run.of(cfg, studies.STATIONARY, studies.RING, RING_TITLE)
    dynamic = Run.of(cfg, studies.DYNAMIC, r120, DYNAMIC_TITLE)
    isolated = Run.of(cfg, studies.DYNAMIC, studies.NONE, ISOLATED_TITLE, algs=("diskf", "cdrkf", "kcf"))
    windows = [Run.variants(cfg, name, st, title, studies.window_variants)
               for name, st, title in ((studies.STATIONARY, studies.RING, WINDOW_RING_TITLE),
                                       (studies.DYNAMIC, r120, DYNAMIC_TITLE))]
    return (dynamic_figures(dynamic, sweep, dyn, out) + stationary_figures(ring, out) + isolated_figure(isolated, out)
            + window_figures(*windows, out))
