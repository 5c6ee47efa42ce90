"""Your own data as a trace: measurements you logged (here made up with numpy,
as a stand-in for your sensors' logs) written as a diskf-trace/1 document,
then every estimator run on it, with the error against the truth you know.

    python examples/own-data/run.py [--out trace.json] [--ticks 150]

The document's fields are described in docs/formats.md (diskf-trace/1). With
real data, leave ``truth`` out: the estimates come without metrics.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

import diskf_mesh


def logged_data(ticks: int, rng: np.random.Generator) -> dict:
    """Three sensors watching a 2-D target that drifts, then turns: sensor 1
    sees x, sensor 2 sees y, sensor 3 sees both but drops out half the time.
    Sensors 1 and 3 and sensors 2 and 3 talk; 1 and 2 do not."""
    A = np.eye(2)
    G = np.array([[1.0, 0.0], [0.0, 1.0]])             # the unknown input is a 2-D velocity
    Q = 0.1 * np.eye(2)
    d = np.where(np.arange(ticks)[:, None] < ticks // 2, [1.0, 0.0], [0.0, -1.5])  # the manoeuvre
    x = np.zeros((ticks, 2))
    prev = np.zeros(2)
    for k in range(ticks):
        prev = A @ prev + G @ d[k] + rng.multivariate_normal(np.zeros(2), Q)
        x[k] = prev
    H = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.eye(2)]
    R = [np.array([[1.0]]), np.array([[1.0]]), 4.0 * np.eye(2)]
    y = []
    for k in range(ticks):
        row = []
        for i in range(3):
            if i == 2 and rng.random() < 0.5:
                row.append(None)                          # no measurement this tick
            else:
                row.append((H[i] @ x[k] + rng.multivariate_normal(np.zeros(len(R[i])), R[i])).tolist())
        y.append(row)
    return {
        "format": "diskf-trace/1",
        "A": A.tolist(), "G": G.tolist(), "Q": Q.tolist(),
        "x0": [0.0, 0.0], "P0": np.eye(2).tolist(),
        "agents": [{"id": f"sensor-{i + 1}", "H": H[i].tolist(), "R": R[i].tolist()} for i in range(3)],
        "y": y,
        "links": [[1, 0, 1], [0, 1, 1], [1, 1, 1]],
        "truth": {"x": x.tolist(), "d": d.tolist()},
        "estimator": {"window": 5},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="trace.json", help="where to write the trace (default: trace.json)")
    ap.add_argument("--ticks", type=int, default=150)
    args = ap.parse_args()

    doc = logged_data(args.ticks, np.random.default_rng(7))
    with open(args.out, "w") as f:
        json.dump(doc, f)
    trace = diskf_mesh.read_trace(args.out)               # checked against the format's schema
    print(f"{args.out}: {trace.shape[1]} ticks, agents {', '.join(map(str, trace.agent_labels))}")
    print(f"{'estimator':<14}{'MAE(state)':>12}{'MAE(input)':>12}")
    for name in ("diskf", "diskf-r", "cdrkf", "kcf", "diffkf"):
        run = diskf_mesh.replay(args.out, name)
        m = run.metrics
        print(f"{name:<14}{m['mae_state']:>12.3f}{m['mae_input']:>12.3f}")
    est = diskf_mesh.replay(args.out, "diskf-r").to_dict()   # a diskf-estimates/1 document
    print(f"estimates document: {est['format']}, x of shape {np.shape(est['x'])} (ticks, agents, n)")


if __name__ == "__main__":
    main()
