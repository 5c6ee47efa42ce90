"""Comparing estimators with a plot: every built-in estimator on the paper's
Scenario 1 with 1-hop (ring) communication, the position error over time
(mean over agents and seeds), one line per estimator, saved as a figure.

    python examples/compare-estimators/run.py [--seeds 5] [--ticks 200] [--out compare.png]

Needs matplotlib (``pip install '.[figures]'`` in the diskf-mesh folder).
"""
from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")  # no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import diskf_mesh  # noqa: E402

ESTIMATORS = ("diskf", "diskf-r", "cdrkf", "ldrkf", "kcf", "diffkf", "gdkf")


def position_error(run) -> np.ndarray:
    """(K,) the mean over seeds and agents of the distance between each
    agent's fused position and the true one."""
    dims = list(run.trace.position_dims)
    truth = run.trace.truth_x[:, :, None, dims]           # (B, K, 1, 2)
    return np.linalg.norm(run.x[..., dims] - truth, axis=-1).mean(axis=(0, 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--ticks", type=int, default=200)
    ap.add_argument("--out", default="compare.png")
    args = ap.parse_args()

    # one trace for all, so every estimator sees the same measurements
    trace = diskf_mesh.simulate("quadrants", seeds=args.seeds, steps=args.ticks, topology="ring")
    scn = diskf_mesh.load_scenario("quadrants")
    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    ticks = np.arange(1, args.ticks + 1)
    for name in ESTIMATORS:
        run = diskf_mesh.estimate(trace, name, scenario=scn)
        ax.plot(ticks, position_error(run), label=f"{name} (MAE {run.metrics['mae_state']:.1f})", lw=1.4)
        print(f"{name:<8} MAE(state) {run.metrics['mae_state']:8.2f}  MAE(input) {run.metrics['mae_input']:8.2f}")
    ax.set_yscale("log")
    ax.set_xlabel("tick")
    ax.set_ylabel("position error (length units), mean over agents and seeds")
    ax.set_title(f"Scenario 1, 1-hop ring, {args.seeds} seeds")
    ax.legend(ncol=2, fontsize=8)
    fig.savefig(args.out, dpi=120)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
