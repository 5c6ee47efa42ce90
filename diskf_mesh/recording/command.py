"""``diskf-mesh replay RUN.mcap [--out EST.json]`` (``commands.replay``
hands a .mcap here)."""
from __future__ import annotations

import sys

from diskf_mesh.data import metrics, provenance
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.outputs import json_safe, save_json
from diskf_mesh.data.trace import estimates_to_json
from diskf_mesh.recording.reader import read, take_ticks
from diskf_mesh.recording.replay import compare, replay


def replay_recording(path, out=None, argv=None) -> int:
    """Exit status 0 when the replay equals the recording bit for bit, 1 if not."""
    started = provenance.now()
    rec = read(path)
    if not rec.ticks:
        raise InputError("recording", f"{path} holds no complete tick to replay")
    est = replay(rec)
    scores = metrics.compute(take_ticks(rec.trace, rec.ticks), est) if rec.ticks else None
    c = compare(rec, est)
    if out:
        run = rec.run.get("provenance") or {}
        prov = provenance.record(
            scenario=run.get("scenario") or {"name": rec.run.get("scenario_name"), "sha256": None},
            seeds=[rec.run.get("seed", 0)], ticks=rec.ticks, estimator=rec.algorithm,
            settings=rec.run.get("params"), faults=rec.run.get("faults"),
            status="equal" if c.equal else "differs", started=started, argv=argv)
        save_json(out, provenance.attach(estimates_to_json(est, rec.algorithm, 0, scores, ids=rec.ids), prov))
    cut = "" if rec.ticks == rec.planned_ticks else f" (of {rec.planned_ticks} planned: the recording was cut short)"
    print(f"{rec.algorithm}: {rec.ticks} ticks{cut}, {len(rec.ids)} agents replayed on what each agent fused"
          + (f" -> {out}" if out else ""))
    if c.equal:
        print(f"  equal to the recording bit for bit: x, P, d of {c.agent_ticks} reported agent-ticks")
    else:
        print(f"  differs from the recording at {c.differing} of {c.agent_ticks} agent-ticks "
              f"(largest |difference| {c.max_abs:.3g})", file=sys.stderr)
    for key, value in json_safe(scores or {}).items():
        print(f"  {key:<15}{'-' if value is None else f'{value:.4f}'}")
    return 0 if c.equal else 1
