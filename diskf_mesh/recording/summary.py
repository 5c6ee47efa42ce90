"""What ``diskf-mesh inspect RUN.mcap`` prints: a recording in numbers."""
from __future__ import annotations

from collections import Counter

from diskf_mesh.data import metrics
from diskf_mesh.recording.reader import Recording, take_ticks

VERDICTS = ("fused", "lost", "late", "rejected", "unreported")


def recorded_metrics(rec: Recording) -> dict:
    """``experiment``'s metrics of the recorded estimates over the reported agent-ticks."""
    if not rec.reported.any():
        return {}
    trace = take_ticks(rec.trace, rec.ticks)
    return metrics.summarize(*metrics.errors(trace, rec.estimates(fill=True)), mask=rec.reported[None])


def summary(rec: Recording) -> dict:
    run = rec.run
    verdicts = Counter(doc["verdict"] for doc in rec.delivered)
    reasons = Counter(doc.get("reason", "") for doc in rec.delivered if doc["verdict"] == "rejected")
    return {
        "file": rec.path,
        "format": run["format"],
        "finished": rec.finished,
        "status": (rec.result or {}).get("status", "cut short" if not rec.finished else "unknown"),
        "run_status": {k: v for k, v in ((rec.result or {}).get("verification") or {}).items()
                       if k in ("status", "reason")},
        "run_id": run["run_id"],
        "scenario": run["scenario"],
        "algorithm": run["algorithm"],
        "seed": run["seed"],
        "topology": run["topology"],
        "comm_range": run["comm_range"],
        "faults": {k: v for k, v in run["faults"].items() if v and (k != "reorder_ms" or run["faults"]["reorder"])},
        "versions": run["versions"],
        "ticks": rec.ticks,
        "planned_ticks": rec.planned_ticks,
        "agents": len(rec.ids),
        "ids": list(rec.ids),
        "reported": int(rec.reported.sum()),
        "agent_ticks": int(rec.reported.size),
        "messages": {
            "sent": len(rec.sent),
            "fused_unlike_sent": sum(len(doc.get("differs", ())) for doc in rec.sent),
            "delivered": {v: verdicts.get(v, 0) for v in VERDICTS},
            "rejected": dict(sorted(reasons.items())),
            "duplicate_copies": sum(max(doc.get("copies", 1) - 1, 0) for doc in rec.delivered),
        },
        "metrics": recorded_metrics(rec),
    }


def format_summary(s: dict) -> str:
    m = s["messages"]
    faults = ", ".join(f"{k} {v:g}" for k, v in s["faults"].items()) or "none"
    ticks = (f"{s['ticks']} of {s['planned_ticks']}" if s["ticks"] != s["planned_ticks"] else f"{s['ticks']}")
    state = "complete" if s["finished"] else "cut short (no footer): read up to its last closed tick"
    lines = [
        f"{s['file']}: {s['format']}, {state}; status {s['status']}",
        ("checked by the engine at the run's end: " + (f"{s['run_status']['status']}: {s['run_status']['reason']}"
                                                       if s["run_status"] else "not recorded (replay checks it)")),
        f"run {s['run_id']}: scenario {s['scenario']}, "
        + (f"range {s['comm_range']:g}" if s["topology"] == "range" else f"topology {s['topology']}")
        + f", {s['algorithm']}, seed {s['seed']}, faults: {faults}",
        "versions: " + ", ".join(f"{k} {v}" for k, v in s["versions"].items()),
        f"ticks: {ticks}; agents: {s['agents']} (ids {', '.join(map(str, s['ids']))}); "
        f"reports: {s['reported']} of {s['agent_ticks']} agent-ticks",
        f"messages sent: {m['sent']}"
        + (f" ({m['fused_unlike_sent']} fused with another digest than sent)" if m["fused_unlike_sent"] else ""),
        "delivered, per linked receiver: " + ", ".join(f"{v} {n}" for v, n in m["delivered"].items())
        + f"; duplicate copies {m['duplicate_copies']}",
    ]
    if m["rejected"]:
        lines.append("rejected by reason: " + ", ".join(f"{r} {n}" for r, n in m["rejected"].items()))
    if s["metrics"]:
        names = {"mae_state": "MAE(state)", "rmse_state": "RMSE(state)", "mae_input": "MAE(input)",
                 "rmse_input": "RMSE(input)", "input_coverage": "input cov.", "nees": "NEES"}
        lines.append("metrics of the recorded estimates: " + ", ".join(
            f"{names[k]} {v:.4g}" for k, v in s["metrics"].items() if k in names))
    return "\n".join(lines)
