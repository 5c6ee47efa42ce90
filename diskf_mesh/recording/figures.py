"""``diskf-mesh figures --from RUN.mcap --out DIR``: one recorded run drawn.

    run-trajectories.png  the target's true path, each agent's estimated
                          position over the run, and where the agents went
    run-links.png         links in range per tick, and what became of the
                          messages on them (fused, lost, late, rejected)
    run-error.png         each agent's position error against time, and
                          the mean over the agents that reported

Coordinates are the scenario's (it gives no unit).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from diskf_mesh.recording.reader import Recording, take_ticks
from diskf_mesh.recording.scene import AGENT_COLORS, agent_color
from diskf_mesh.recording.summary import VERDICTS

VERDICT_COLORS = {"fused": "tab:green", "lost": "tab:red", "late": "tab:orange", "rejected": "tab:purple",
                  "unreported": "0.6"}


def _title(rec: Recording) -> str:
    run = rec.run
    faults = ", ".join(f"{k} {v:g}" for k, v in run["faults"].items() if v and k != "reorder_ms") or "no faults"
    cut = "" if rec.ticks == rec.planned_ticks else f" of {rec.planned_ticks}"
    return f"{run['scenario']}, {run['algorithm']}, seed {run['seed']}, {rec.ticks}{cut} ticks, {faults}"


def _agent_colors(N: int):
    from matplotlib import colormaps

    if N <= len(AGENT_COLORS):  # as in the recording's /scene
        return [agent_color(j) for j in range(N)]
    cmap = colormaps["viridis"]
    return [cmap(i / max(N - 1, 1)) for i in range(N)]


def plot_trajectories(rec: Recording, path: Path) -> Path:
    from diskf_mesh.studies.figures import TRUTH_COLOR, _figure, _save

    trace = take_ticks(rec.trace, rec.ticks)
    dims = list(trace.position_dims)[:2]
    truth = trace.truth_x[0][:, dims]
    colors = _agent_colors(len(rec.ids))
    fig = _figure(11.0, 5.4, top=0.86, wspace=0.25)
    ax_est, ax_pos = fig.subplots(1, 2)
    for j, i in enumerate(rec.ids):
        est = np.where(rec.reported[:, j, None], rec.x[:, j][:, dims], np.nan)
        ax_est.plot(*est.T, color=colors[j], lw=0.8, alpha=0.8, label=f"agent {i}")
    ax_est.plot(*truth.T, color=TRUTH_COLOR, lw=1.4, label="truth", zorder=5)
    ax_est.plot(*truth[0], "o", color=TRUTH_COLOR, ms=5, zorder=5)
    span = np.ptp(truth, axis=0).max() or 1.0
    lo, hi = truth.min(axis=0) - 0.4 * span, truth.max(axis=0) + 0.4 * span
    ax_est.set_xlim(lo[0], hi[0])
    ax_est.set_ylim(lo[1], hi[1])
    ax_est.set_title("target: truth (olive, o = tick 1) and each agent's estimate", fontsize=10)
    ax_est.legend(fontsize=7, ncol=2, loc="upper right", framealpha=0.6)
    pos = rec.positions
    for j, i in enumerate(rec.ids):
        p = pos[:, j]
        moving = np.ptp(p, axis=0).max() > 0
        if moving:
            ax_pos.plot(*p.T, color=colors[j], lw=1.0)
        ax_pos.plot(*p[-1], "o" if moving else "s", color=colors[j], ms=7)
        ax_pos.annotate(str(i), p[-1], xytext=(4, 4), textcoords="offset points", fontsize=8)
    last = rec.edges[-1] if rec.edges else []
    where = {i: j for j, i in enumerate(rec.ids)}
    for a, b in last:
        ax_pos.plot(*pos[-1, [where[a], where[b]]].T, color="tab:blue", lw=0.8, alpha=0.7)
    ax_pos.plot(*truth.T, "--", color=TRUTH_COLOR, lw=0.8, label="target (truth)")
    ax_pos.legend(fontsize=7, loc="upper right", framealpha=0.6)
    ax_pos.set_title(f"agents: paths, positions and links at tick {rec.ticks} (square = static)", fontsize=10)
    for ax, adjust in ((ax_est, "box"), (ax_pos, "datalim")):
        ax.set_xlabel("x (scenario units)")
        ax.set_ylabel("y (scenario units)")
        ax.set_aspect("equal", adjustable=adjust)
        ax.grid(alpha=0.3)
    fig.suptitle(f"Trajectories: {_title(rec)}")
    return _save(fig, path)


def verdicts_per_tick(rec: Recording) -> dict:
    """{verdict: (K,) counts of linked (sender, receiver) pairs per tick}."""
    out = {v: np.zeros(rec.ticks, dtype=int) for v in VERDICTS}
    for doc in rec.delivered:
        out[doc["verdict"]][doc["tick"] - 1] += 1
    return out


def plot_links(rec: Recording, path: Path) -> Path:
    from diskf_mesh.studies.figures import _figure, _save

    t = np.arange(1, rec.ticks + 1)
    fig = _figure(9.0, 6.0, top=0.9, hspace=0.3)
    ax_links, ax_msgs = fig.subplots(2, 1, sharex=True)
    ax_links.plot(t, [len(e) for e in rec.edges], color="tab:blue", lw=1.5, drawstyle="steps-mid")
    ax_links.set_ylabel("links in range")
    ax_links.set_title("link graph: pairs of live agents within range", fontsize=10)
    counts = verdicts_per_tick(rec)
    bottom = np.zeros(rec.ticks)
    for v in VERDICTS:
        if counts[v].any():
            ax_msgs.bar(t, counts[v], bottom=bottom, width=1.0, color=VERDICT_COLORS[v],
                        label=f"{v} ({counts[v].sum()})")
            bottom += counts[v]
    ax_msgs.set_ylabel("messages (sender → receiver)")
    ax_msgs.set_xlabel("tick k")
    ax_msgs.set_title("what became of each message at each linked receiver", fontsize=10)
    ax_msgs.legend(fontsize=8, loc="upper right")
    for ax in (ax_links, ax_msgs):
        ax.grid(alpha=0.3)
        ax.set_xlim(0.5, rec.ticks + 0.5)
    fig.suptitle(f"Links over time: {_title(rec)}")
    return _save(fig, path)


def position_errors(rec: Recording) -> np.ndarray:
    """(K, N) distance of each agent's estimated position to the truth, NaN where it did not report."""
    dims = list(rec.trace.position_dims)
    truth = rec.trace.truth_x[0, :rec.ticks][:, None, dims]
    err = np.linalg.norm(rec.x[..., dims] - truth, axis=-1)
    return np.where(rec.reported, err, np.nan)


def plot_error(rec: Recording, path: Path) -> Path:
    from diskf_mesh.studies.figures import _figure, _save

    t = np.arange(1, rec.ticks + 1)
    err = position_errors(rec)
    colors = _agent_colors(len(rec.ids))
    fig = _figure(9.0, 4.6, top=0.87)
    ax = fig.subplots()
    for j, i in enumerate(rec.ids):
        ax.plot(t, err[:, j], color=colors[j], lw=0.8, alpha=0.75, label=f"agent {i}")
    with np.errstate(invalid="ignore"):
        mean = np.nanmean(np.where(rec.reported, err, np.nan), axis=1) if rec.reported.any() else t * np.nan
    ax.plot(t, mean, color="k", lw=2.0, label="mean")
    ax.set_yscale("log")
    ax.set_xlabel("tick k")
    ax.set_ylabel("position error (scenario units, log)")
    ax.set_xlim(0.5, rec.ticks + 0.5)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=5, loc="upper right")
    fig.suptitle(f"Error over time: {_title(rec)}")
    return _save(fig, path)


def make_recording_figures(rec: Recording, out_dir, fmt: str = "png") -> list:
    from diskf_mesh.studies.figures import _Folder

    out = _Folder(out_dir, fmt)
    if not rec.ticks:
        return []
    return [plot_trajectories(rec, out / "run-trajectories"), plot_links(rec, out / "run-links"),
            plot_error(rec, out / "run-error")]
