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


def summary(rec: Recording, recheck: bool = False) -> dict:
    """The recording in numbers; its run's verdict as the run recorded it,
    or with ``recheck`` the engine's verdict now (``replay.recording_status``)."""
    run = rec.run
    if recheck:
        from diskf_mesh.recording.replay import recording_status

        st = recording_status(rec)
        verdict = {"status": st.status, "reason": st.reason, "rechecked": True}
    else:
        stored = (rec.result or {}).get("verification") or {}
        verdict = {**{k: v for k, v in stored.items() if k in ("status", "reason")}, "rechecked": False}
    verdicts = Counter(doc["verdict"] for doc in rec.delivered)
    reasons = Counter(doc.get("reason", "") for doc in rec.delivered if doc["verdict"] == "rejected")
    return {
        "file": rec.path,
        "format": run["format"],
        "finished": rec.finished,
        "whole": not rec.not_whole(),
        "not_whole": rec.not_whole() or None,
        "status": (rec.result or {}).get("status", "cut short" if not rec.finished else "unknown"),
        "run_status": verdict,
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
    state = "whole" if s["whole"] else f"not whole, read up to its last whole tick ({s['not_whole']})"
    v = s["run_status"]
    lines = [
        f"{s['file']}: {s['format']}, {state}; status {s['status']}",
        (f"re-checked by the engine now: {v['status']}: {v['reason']}" if v["rechecked"] else
         "as the run's own check recorded it, not re-checked (replay or inspect --check re-checks it): "
         + (f"{v['status']}: {v['reason']}" if "status" in v else "none recorded")),
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
