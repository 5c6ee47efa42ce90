"""``diskf-mesh replay RUN.mcap [--out EST.json]`` (``commands.replay``
hands a .mcap here): the recorded run checked again by the engine."""
from __future__ import annotations

import sys

from diskf_mesh.data import metrics, provenance
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.outputs import json_safe, save_json
from diskf_mesh.data.trace import estimates_to_json
from diskf_mesh.mesh.run_status import accept
from diskf_mesh.recording.reader import read, take_ticks
from diskf_mesh.recording.replay import recording_status, replay


def replay_recording(path, out=None, argv=None, allow_missing: float = 0.0, allow_degraded: bool = False) -> int:
    """The recording's status (``recording_status``) and its exit status
    (``run_status.accept``: 0 for exact and as planned, or a status the
    flags accept; ``core.exits``)."""
    started = provenance.now()
    rec = read(path)
    if not rec.ticks:
        raise InputError("recording", f"{path} holds no complete tick to replay")
    status = recording_status(rec)
    est = replay(rec)
    scores = metrics.compute(take_ticks(rec.trace, rec.ticks), est) if rec.ticks else None
    if out:
        run = rec.run.get("provenance") or {}
        prov = provenance.record(
            scenario=run.get("scenario") or {"name": rec.run.get("scenario_name"), "sha256": None},
            seeds=[rec.run.get("seed", 0)], ticks=rec.ticks, estimator=rec.algorithm,
            settings=rec.run.get("params"), faults=rec.run.get("faults"),
            status=status.status, started=started, argv=argv)
        save_json(out, provenance.attach(estimates_to_json(est, rec.algorithm, 0, scores, ids=rec.ids), prov))
    cut = "" if rec.ticks == rec.planned_ticks else f" (of {rec.planned_ticks} planned: the recording was cut short)"
    ev = status.evidence
    print(f"{rec.algorithm}: {rec.ticks} ticks{cut}, {len(rec.ids)} agents replayed on what each agent fused"
          + (f", {len(ev.get('restarts', ()))} restarts" if ev.get("restarts") else "") + (f" -> {out}" if out else ""))
    print(f"  {status.status}: {status.reason}")
    print(f"  reproduced bit for bit: x, P, d of {ev['reported'] - ev['differing']} of {ev['reported']} reported "
          f"agent-ticks; {ev['digests_checked']} fused messages' digests checked")
    for key, value in json_safe(scores or {}).items():
        print(f"  {key:<15}{'-' if value is None else f'{value:.4f}'}")
    code, level, line = accept(status, allow_missing=allow_missing, allow_degraded=allow_degraded)
    if level:
        print(f"{level}: replay: {line}", file=sys.stderr)
    return code
