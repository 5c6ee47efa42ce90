"""``diskf-mesh replay RUN.mcap [--out EST.json]`` (``commands.replay``
hands a .mcap here): the recorded run checked again by the engine.
``report_replay`` ends it, and ``replay TRACE --fused EST``."""
from __future__ import annotations

import sys

from diskf_mesh.core import exits
from diskf_mesh.data import metrics, provenance
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.outputs import human_stream, json_safe, save_json
from diskf_mesh.data.trace import estimates_to_json
from diskf_mesh.mesh.protocol.run_status import accept
from diskf_mesh.recording.reader import read, take_ticks
from diskf_mesh.recording.replay import recorded_miss_rate, recording_status, replay


def replay_recording(path, out=None, argv=None, allow_missing: float = 0.0, allow_degraded: bool = False,
                     accept_unverifiable: bool = False) -> int:
    """The recording's status (``recording_status``) and its exit status
    (``report_replay``); a recording that is not whole exits ``INCOMPLETE``
    (or ``DIVERGED``) whatever the tolerances."""
    started = provenance.now()
    rec = read(path)
    if not rec.ticks:
        raise InputError("recording", f"{path} holds no complete tick to replay"
                         + (f" ({rec.damage})" if rec.damage else ""))
    status = recording_status(rec)
    run = rec.run.get("provenance") or {}
    prov = provenance.record(
        scenario=run.get("scenario") or {"name": rec.run.get("scenario_name"), "sha256": None},
        seeds=[rec.run.get("seed", 0)], ticks=rec.ticks, estimator=rec.algorithm,
        settings=rec.run.get("params"), faults=rec.run.get("faults"),
        status=status.status, started=started, argv=argv)
    cut = "" if rec.ticks == rec.planned_ticks else f" (of {rec.planned_ticks} planned)"
    return report_replay(status, replay(rec), rec.trace, rec.algorithm, rec.ids, prov, out,
                         miss_rate=recorded_miss_rate(rec), allow_missing=allow_missing,
                         allow_degraded=allow_degraded, accept_unverifiable=accept_unverifiable, cut=cut)


def report_replay(status, est, trace, algorithm: str, ids, prov: dict, out=None, *, miss_rate=None,
                  allow_missing: float = 0.0, allow_degraded: bool = False, accept_unverifiable: bool = False,
                  cut: str = "", hint: str = "") -> int:
    """The end of a replayed run (``replay RUN.mcap``, ``replay TRACE --fused
    EST``): ``est``, the engine on what each agent fused (ticks 1..K),
    scored on ``trace``'s truth and written to ``out`` with ``prov``; what
    was replayed, the run's ``status`` and the scores in lines (on stderr
    when ``out`` is standard output); the exit status
    (``run_status.accept``). A real-time run (``miss_rate`` given) was
    judged against its ``--max-miss-rate`` by the run: here its deadline
    misses are accepted, as the run accepted them. ``hint`` follows the
    error line when no reported estimate is reproduced. A recording that is
    not whole (``status.evidence["recording"]``) is never accepted."""
    K = est.x.shape[1]
    scores = metrics.compute(take_ticks(trace, K), est) if trace.truth_x is not None else None
    if out:
        save_json(out, provenance.attach(estimates_to_json(est, algorithm, 0, scores, ids=ids), prov))
    text, ev = human_stream(out), status.evidence
    print(f"{algorithm}: {K} ticks{cut}, {len(ids)} agents replayed on what each agent fused"
          + (f", {len(ev['restarts'])} restarts" if ev.get("restarts") else "") + (f" -> {out}" if out else ""),
          file=text)
    print(f"  {status.status}: {status.reason}", file=text)
    print(f"  reproduced bit for bit: x, P, d of {ev['reported'] - ev['differing']} of {ev['reported']} reported "
          f"agent-ticks; {ev['digests_checked']} fused messages' digests checked", file=text)
    for key, value in json_safe(scores or {}).items():
        print(f"  {key:<15}{'-' if value is None else f'{value:.4f}'}", file=text)
    code, level, line = accept(status, allow_missing=allow_missing, allow_degraded=allow_degraded,
                               accept_unverifiable=accept_unverifiable, miss_rate=miss_rate,
                               max_miss_rate=None if miss_rate is None else 1.0)
    if (ev.get("recording") or {}).get("whole") is False and code == exits.OK:
        code, level, line = exits.INCOMPLETE, "error", f"{status.status}: {status.reason}"  # no tolerance accepts it
    if level:
        print(f"{level}: replay: {line}" + (f" ({hint})" if hint and ev["differing"] == ev["reported"] else ""),
              file=sys.stderr)
    return code
