"""What the live view shows, tick by tick, and how it goes to Rerun.

``LiveView`` turns the samples a watcher hears on the mesh (the world's
ticks, the agents' reports) into one ``Frame`` per tick; ``take`` hands
out the newest one not taken yet (a view drawing at its own pace skips the
ticks in between: the mesh ticks faster than a screen needs). The truth is not on the wire: it is recomputed here from the scenario
and the seed (``scenario.simulate`` is deterministic, so it is the world's).
A frame is complete when the next tick opens (the world opens tick k+1 only
after every live agent reported tick k, or at its deadline) or when the run
stops; a report that comes after its frame went out is counted in ``late``
and not shown.

``scene_doc`` and ``frame_doc`` are what the page (``page.html``) draws:
the agents (static red, mobile green, grey when not live), the links of the
tick between live agents, the target (blue) and its recent true path, each
agent's fused position (yellow) and its 95 % covariance ellipse, each
agent's position error and the running MAE over the agent-ticks reported so
far (as ``metrics.errors`` and ``metrics.summarize`` define them), and every
agent's message counters.
"""
from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from diskf_mesh.data import metrics
from diskf_mesh.mesh import wire
from diskf_mesh.mesh.counters import Counters
from diskf_mesh.engine.batch import Estimates
from diskf_mesh.data.scenario import Scenario, links_for
from diskf_mesh.data.trace import Trace

CHI2_95_2D = 5.991464547107979  # 95 % quantile of the chi-square law with 2 degrees of freedom
ELLIPSE_POINTS = 33             # closed polygon: the last point repeats the first

# colours (RGB): agents as in the paper's figure (static red, mobile green)
STATIC = (230, 60, 60)
MOBILE = (60, 200, 80)
GONE = (110, 110, 110)
TRUTH = (40, 170, 255)
ESTIMATE = (250, 200, 40)
LINK = (170, 170, 170)
COUNTER_COLUMNS = ("published", "sent", "received", "fused", "lost", "late", "duplicate", "unlinked")


def covariance_ellipses(mean: np.ndarray, P: np.ndarray, scale2: float = CHI2_95_2D,
                        points: int = ELLIPSE_POINTS) -> np.ndarray:
    """(..., points, 2): the ellipses {x : (x - mean)^T P^-1 (x - mean) = scale2}
    of 2-D means (..., 2) and covariances (..., 2, 2), as closed polygons.
    x = mean + sqrt(scale2) L u over the unit circle u, with P = L L^T."""
    t = np.linspace(0.0, 2.0 * math.pi, points)
    circle = np.stack([np.cos(t), np.sin(t)])                 # (2, points)
    L = np.linalg.cholesky(P)                                  # (..., 2, 2)
    return mean[..., None, :] + math.sqrt(scale2) * np.swapaxes(L @ circle, -1, -2)


@dataclass
class Frame:
    """Everything the view shows of tick k (arrays in scenario order)."""

    tick: int
    positions: np.ndarray                  # (N, 2)
    live: np.ndarray                       # (N,) bool
    links: list                            # [(i, j)] indices, i < j, both live
    truth: np.ndarray                      # (2,) target position
    reported: np.ndarray                   # (N,) bool
    estimate: np.ndarray                   # (N, 2), NaN where not reported
    cov: np.ndarray                        # (N, 2, 2), NaN where not reported
    error: np.ndarray                      # (N,), NaN where not reported
    running_mae: float                     # over every agent-tick reported so far (NaN before any)
    counters: dict = field(default_factory=dict)  # id -> counters of its latest report


class LiveView:
    """Collects the ticks and reports of one run into frames (thread-safe:
    zenoh calls ``on_tick``/``on_report`` from its network thread).

    A tick's frame is made, in tick order, once every agent of its
    live set reported, or once a tick ``WAIT_TICKS`` later has opened (the
    reports come on other links than the ticks, and may come after the next
    tick: the world opens it as soon as it has them), or at the stop."""

    WAIT_TICKS = 25

    def __init__(self, scn: Scenario, trace: Trace):
        self.scn, self.trace = scn, trace
        self.ids = tuple(a.id for a in scn.agents)
        self.index = {i: j for j, i in enumerate(self.ids)}
        self.dims = list(trace.position_dims)
        self.n, self.m = trace.model.n, trace.model.m
        self.frames = 0            # frames made
        self.last_tick = 0         # tick of the last frame
        self._latest: Frame | None = None  # the newest frame, until taken
        self.late = 0              # reports that came after their frame
        self._lock = threading.Lock()
        self._ticks: dict = {}     # tick -> wire.Tick, not shown yet
        self._reports: dict = {}   # tick -> {id: Report}, not shown yet
        self._counters: dict = {}  # id -> counters of its latest report shown
        self._err_sum = 0.0
        self._err_count = 0

    def on_tick(self, t: wire.Tick) -> None:
        with self._lock:
            if t.tick <= self.last_tick or not 1 <= t.tick <= self.trace.has.shape[1]:
                return  # a repeat, or a tick older than the one shown
            self._ticks[t.tick] = t
            self._advance()

    def on_report(self, r: wire.Report) -> None:
        with self._lock:
            if r.tick <= self.last_tick:
                self.late += 1
                return
            self._reports.setdefault(r.tick, {})[r.sender] = r
            self._advance()

    def take(self) -> Frame | None:
        """The newest frame if it was not taken yet, else None."""
        with self._lock:
            f, self._latest = self._latest, None
            return f

    def on_stop(self) -> None:
        with self._lock:
            self._advance(final=True)

    def _advance(self, final: bool = False) -> None:
        """Lock held: every frame that is due, oldest first."""
        while self._ticks:
            k = min(self._ticks)
            t, got = self._ticks[k], self._reports.get(k, {})
            if not (final or all(i in got for i in t.live) or max(self._ticks) >= k + self.WAIT_TICKS):
                return
            del self._ticks[k]
            self._reports = {j: v for j, v in self._reports.items() if j > k}
            for sender, r in sorted(got.items()):
                self._counters[sender] = r.counters
            self._latest = self._frame(t, got)
            self.frames += 1
            self.last_tick = k

    def _frame(self, t: wire.Tick, reports: dict) -> Frame:
        N, k = len(self.ids), t.tick
        live = np.array([i in t.live for i in self.ids])
        L = links_for(self.scn, t.positions[None])[0] & live[:, None] & live[None, :]
        links = [(i, j) for i, j in zip(*np.nonzero(np.triu(L, 1)))]
        x = np.full((N, self.n), np.nan)
        P = np.broadcast_to(np.eye(self.n), (N, self.n, self.n)).copy()
        d = np.zeros((N, self.m))
        dv = np.zeros(N, dtype=bool)
        reported = np.zeros(N, dtype=bool)
        for sender, r in reports.items():
            j = self.index[sender]
            x[j], P[j], d[j], dv[j], reported[j] = r.x, r.P, r.d, r.d_valid, True
        one_tick = dataclasses.replace(self.trace, truth_x=self.trace.truth_x[:1, k - 1:k],
                                       truth_d=self.trace.truth_d[:1, k - 1:k])
        est = Estimates(np.where(reported[:, None], x, 0.0)[None, None], P[None, None], d[None, None],
                        dv[None, None])
        e_state = metrics.errors(one_tick, est)[0][0, 0]
        error = np.where(reported, e_state, np.nan)
        self._err_sum += float(e_state[reported].sum())
        self._err_count += int(reported.sum())
        dims = np.ix_(range(N), self.dims, self.dims)
        cov = np.where(reported[:, None, None], P[dims], np.nan)
        return Frame(
            tick=k, positions=np.asarray(t.positions, dtype=float), live=live, links=links,
            truth=self.trace.truth_x[0, k - 1, self.dims], reported=reported,
            estimate=np.where(reported[:, None], x[:, self.dims], np.nan), cov=cov, error=error,
            running_mae=self._err_sum / self._err_count if self._err_count else math.nan,
            counters=dict(self._counters))


# --------------------------------------------------------------------------
# what the page gets
# --------------------------------------------------------------------------
def _num(a) -> list:
    """Floats for JSON, rounded to what a screen shows, NaN as None."""
    return [None if v != v else round(float(v), 3) for v in np.asarray(a, dtype=float).ravel()]


def scene_doc(scn: Scenario, trace: Trace, run_id: str, algorithm: str) -> dict:
    """What does not change during the run: agents, the target's true path, bounds."""
    dims = list(trace.position_dims)
    path = trace.truth_x[0][:, dims]
    pos = trace.positions.reshape(-1, 2)
    both = np.concatenate([path, pos])
    lo, hi = both.min(axis=0), both.max(axis=0)
    pad = 0.05 * float((hi - lo).max() or 1.0)
    return {
        "run_id": run_id, "scenario": scn.name, "algorithm": algorithm, "ticks": int(trace.has.shape[1]),
        "ids": [str(a.id) for a in scn.agents], "mobile": [bool(a.mobile) for a in scn.agents],
        "labels": [("m" if a.mobile else "s") + str(a.name) for a in scn.agents],
        "bounds": _num([lo[0] - pad, lo[1] - pad, hi[0] + pad, hi[1] + pad]),
        "truth_path": [_num(p) for p in path], "counters": list(COUNTER_COLUMNS) + ["rejected"],
        "colors": {"static": STATIC, "mobile": MOBILE, "gone": GONE, "truth": TRUTH, "estimate": ESTIMATE,
                   "link": LINK},
    }


def frame_doc(f: Frame, ids: tuple) -> dict:
    """One frame as the page draws it: positions, links, truth, estimates
    with their 95 % ellipses, errors and every agent's counters."""
    ok = f.reported
    ellipses = np.full((len(ids), ELLIPSE_POINTS, 2), np.nan)
    if ok.any():
        ellipses[ok] = covariance_ellipses(f.estimate[ok], f.cov[ok])
    counters = {}
    for i in ids:
        if i in f.counters:
            c = Counters.from_dict(f.counters[i])
            counters[str(i)] = [getattr(c, k) for k in COUNTER_COLUMNS] + [c.rejected_total]
    return {
        "tick": f.tick, "positions": [_num(p) for p in f.positions], "live": f.live.tolist(),
        "links": [[int(i), int(j)] for i, j in f.links], "truth": _num(f.truth),
        "estimates": [_num(e) if r else None for e, r in zip(f.estimate, ok)],
        "ellipses": [[_num(p) for p in e] if r else None for e, r in zip(ellipses, ok)],
        "errors": _num(f.error), "running_mae": _num([f.running_mae])[0], "counters": counters,
    }
