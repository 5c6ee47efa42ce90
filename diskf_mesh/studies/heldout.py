"""The held-out suite: every estimator on inputs, models and networks no
default was chosen on.

Cases (``cases``): every ``[input]`` kind on both shipped scenarios in every
topology the report shows (Scenario 1: all-to-all, ring, isolated; Scenario
2: range 120 and all-to-all); a constant-velocity model (n = 4) with a small
2-D acceleration input; a 3-D state with p_i = 2 sensors; Scenario 1 with
p_i = 2 sensors, with mixed sensors, with the turn rate omega from 0.05 to
0.6, with R x 0.01 and x 100; random geometric networks of 25 and 50 agents.
Then the grown families (``grown_cases``): a world (``World``) whose
measurement or process noise covariance is 10 or 0.1 times what the
estimators are told, or whose measurements come in bursts of 30 times the
covariance; a world where a fifth of the measurements arrive; two input
channels of different kinds (m = 2, G = I, ``Channels``); the
constant-acceleration model (n = 6) with a small 2-D jerk input.

Per case and estimator (``run_case``): the state MAE, the input MAE, the
mean NEES over the (tick, agent) cells whose neighbourhood measures, and the
share of the cells where every seed's neighbourhood measures whose NEES,
averaged over the S seeds, lies in the chi-square 95 % band of that average
([chi2_{Sn}(0.025), chi2_{Sn}(0.975)] / S, n the state dimension). The mean
NEES target uses the same band (the band of S runs: the cells of one run
are correlated in time, so the far narrower band of every cell taken as
independent would not be honest). A run whose covariance stops being positive
definite, or whose state or input estimate leaves what a message may carry, counts as
diverged (``experiment.run_or_none``). A run that did not diverge but whose
state error at some (tick, agent) passed ``FAR`` times the target's farthest
distance from the origin lost the target (``error_ratio``; an unbiased input
estimate gets there where the sensors that measure leave an invariant zero
outside the unit circle, its error multiplied each measured tick), and it is
counted beside the diverged ones, not left as a number in the tables.

``targets`` checks the suite against the three targets: the DISKF family's
best (every estimator whose name starts with ``diskf``) within 1 % of the
best baseline, ``diskf-auto`` within 10 % of each case's best, and its mean
NEES inside the band for the mean over every observed cell.

``by_silence`` (``--by-silence CASE``) splits one case's state MAE by the
ticks since each agent's own last measurement, for ``diskf-auto`` and each
model of its bank alone: whether a model loses while measured or only
across the ticks no one measures.

``bank_members`` and ``run_bank`` (``--bank``) run each model of
``diskf-auto``'s bank alone (``diskf-r`` with that input model);
``bank_summary`` names, for each case ``diskf-auto`` misses by more than
10 %, the best of them: whether the bank holds a model that fits, or the
choice between its models is what fails.

    python -m diskf_mesh.studies.heldout --seeds 20 --json heldout.json --markdown heldout.md

``--first-seed S`` runs seeds S .. S + seeds - 1 instead of 0 .. seeds - 1:
the same targets on seeds no default was chosen on.

``--estimators a,b --against FILE`` runs only those estimators and takes
every other estimator's rows from a held-out document written before
(``--json``, or a report's ``results.json``) on the same seeds and ticks
(``merge``): a new estimator, or a new default of one, measured on the
whole suite against every shipped one at a ninth of the cost.
``--jobs J`` runs the cases in J processes (the rows are the same).

    python -m diskf_mesh.studies.heldout --estimators diskf-auto --against docs/results.json --jobs 2
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, replace

import numpy as np

from diskf_mesh import estimators as algorithms
from diskf_mesh.data import metrics
from diskf_mesh.data.argtypes import add_ticks
from diskf_mesh.data.inputs import parse_input
from diskf_mesh.data.scenario import Scenario, load_scenario, parse_scenario, simulate
from diskf_mesh.data.trace import Trace
from diskf_mesh.engine import batch as engine
from diskf_mesh.core.model import AutoOptions
from diskf_mesh.estimators import Params
from diskf_mesh.studies import experiment
from diskf_mesh.studies.suite import observed, rotation

FAMILY_PREFIX = "diskf"
AUTO = "diskf-auto"

# the [input] tables of the shipped scenarios' cases (input units: Scenario 1's step is 10)
SHIPPED_INPUTS = {
    "step": None,  # the scenario's own: 0, then 10 from tick 10
    "zero": dict(kind="constant", value=0.0),
    "constant 5": dict(kind="constant", value=5.0),
    "sine fast": dict(kind="sine", amplitude=10.0, period=10.0),
    "sine slow": dict(kind="sine", amplitude=10.0, period=80.0),
    "steps": dict(kind="steps", scale=10.0, interval=30.0),
    "telegraph 3": dict(kind="telegraph", amplitude=10.0, interval=3, random=False),
    "telegraph random": dict(kind="telegraph", amplitude=5.0, interval=10.0),
    "white": dict(kind="white", scale=3.0),
    "ramp": dict(kind="ramp", at=10, slope=0.1),
    "series": dict(kind="series", values=[0.0] * 20 + [8.0] * 40 + [-4.0] * 40 + [2.0 * (k % 10) for k in range(100)]),
}
VARIANT_INPUTS = ("step", "zero", "sine fast")
# the constant-velocity model's 2-D acceleration inputs (about 0.1)
CV_INPUTS = {
    "zero": dict(kind="constant", value=[0.0, 0.0]),
    "steps 0.1": dict(kind="steps", scale=[0.1, 0.1], interval=40.0),
    "sine 0.1": dict(kind="sine", amplitude=[0.1, 0.05], period=60.0),
    "telegraph 0.1": dict(kind="telegraph", amplitude=[0.1, -0.1], interval=20.0),
    "white 0.05": dict(kind="white", scale=[0.05, 0.05]),
}
# a state error this many times the target's farthest distance from the origin: the run lost the target
FAR = 100.0
TOPOLOGIES_1 = (("all", None), ("ring", None), ("none", None))
TOPOLOGIES_2 = (("range", 120.0), ("all", None))


@dataclass(frozen=True)
class World:
    """How the world of a case differs from what its estimators are told
    (the scenario's Q and R): its process noise covariance is ``Q`` x Q,
    its measurement noise covariance ``R`` x R; a burst (each agent's own:
    one starts with probability ``burst_rate`` at a tick and lasts
    ``burst_ticks``) multiplies the measurement noise covariance by
    ``burst``; each agent's measurement arrives at a tick with probability
    ``measured`` (where its scenario lets it measure). Bursts and arrivals
    are drawn from ``numpy.random.default_rng([seed, WORLD_STREAM])``."""

    Q: float = 1.0
    R: float = 1.0
    burst: float = 1.0
    burst_rate: float = 0.0
    burst_ticks: int = 0
    measured: float = 1.0

    def simulate(self, scn: Scenario, seeds) -> Trace:
        """``simulate`` of this world, the trace holding what the
        estimators are told (``scn``'s model and sensors)."""
        truth = replace(scn, Q=self.Q * scn.Q, agents=tuple(replace(a, R=self.R * a.R) for a in scn.agents))
        tr = simulate(truth, seeds)
        y, has = tr.y, tr.has
        if self.burst_rate > 0 or self.measured < 1:
            y, has = y.copy(), has.copy()
            Lr = np.linalg.cholesky(truth.sensors().R)  # (N, p, p)
            p = tr.sensors.p
            valid = np.arange(y.shape[-1])[None, :] < p[:, None]
            for b, s in enumerate(tr.seeds):
                rng = np.random.default_rng([s, WORLD_STREAM])
                K, N = has.shape[1:]
                starts = rng.random((K, N)) < self.burst_rate
                extra = np.einsum("iab,kib->kia", Lr, rng.standard_normal((K, N, y.shape[-1])))
                arrives = rng.random((K, N)) < self.measured
                on = np.zeros((K, N), dtype=bool)
                for k in range(K):
                    on[k] = starts[max(0, k - self.burst_ticks + 1):k + 1].any(axis=0)
                y[b] += np.where((on[..., None] & valid & has[b][..., None]), math.sqrt(max(self.burst - 1, 0)) * extra, 0.0)
                has[b] &= arrives
                y[b] = np.where(has[b][..., None], y[b], 0.0)
        return replace(tr, model=scn.model(tr.y.shape[1]), sensors=scn.sensors(), y=y, has=has)


WORLD_STREAM = 2  # the second entropy word of a world's bursts and arrivals (the input's is 1)


@dataclass(frozen=True)
class Channels:
    """An input whose channels are of different kinds: one ``[input]``
    table per channel (m = 1 each); channel j of simulation seed s draws
    as seed s + j x 10^6 (a random kind's stream of its own)."""

    specs: tuple

    def values(self, steps: int, sim_seed: int = 0) -> np.ndarray:
        return np.concatenate([spec.values(steps, sim_seed + j * 10**6) for j, spec in enumerate(self.specs)], axis=1)


@dataclass(frozen=True)
class Case:
    group: str
    label: str
    scenario: Scenario
    world: World | None = None  # None: the world is what the estimators are told

    def simulate(self, seeds, steps: int | None = None):
        """(the scenario with ``steps``, its trace on ``seeds`` in this case's world)."""
        scn = self.scenario.with_overrides(steps=steps)
        return scn, (simulate(scn, seeds) if self.world is None else self.world.simulate(scn, seeds))


# the constant-acceleration model's 2-D jerk inputs (about 0.01)
CA_INPUTS = {
    "zero": dict(kind="constant", value=[0.0, 0.0]),
    "steps 0.01": dict(kind="steps", scale=[0.01, 0.01], interval=40.0),
    "sine 0.01": dict(kind="sine", amplitude=[0.01, 0.005], period=60.0),
    "white 0.005": dict(kind="white", scale=[0.005, 0.005]),
}
# the worlds whose noise is not what the estimators are told (covariances x 10 and x 0.1)
WRONG_NOISE = {"true R×10": World(R=10.0), "true R×0.1": World(R=0.1), "true Q×10": World(Q=10.0),
               "true Q×0.1": World(Q=0.1)}
BURSTS = World(burst=30.0, burst_rate=0.02, burst_ticks=10)  # about one burst of 10 ticks every 50 per agent
RARE = World(measured=0.2)  # a fifth of the measurements arrive
# per-channel kinds (m = 2, G = I): one [input] table per channel
CHANNEL_INPUTS = {
    "step | sine fast": (dict(kind="step", at=10, before=[0.0], after=[10.0]), SHIPPED_INPUTS["sine fast"]),
    "step | white": (dict(kind="step", at=10, before=[0.0], after=[10.0]), SHIPPED_INPUTS["white"]),
    "zero | sine fast": (SHIPPED_INPUTS["zero"], SHIPPED_INPUTS["sine fast"]),
    "step | zero": (dict(kind="step", at=10, before=[0.0], after=[10.0]), SHIPPED_INPUTS["zero"]),
}

def _with_input(scn: Scenario, table) -> Scenario:
    return scn if table is None else replace(scn, input=parse_input(table, scn.G.shape[1]))


def _topo(scn: Scenario, topology: str, comm_range) -> Scenario:
    return scn.with_overrides(topology=topology, comm_range=comm_range)


def _topo_label(topology: str, comm_range) -> str:
    return f"range {comm_range:g}" if topology == "range" else topology


def constant_velocity(topology: str) -> Scenario:
    """n = 4 (x, vx, y, vy), one tick per step, an acceleration input of
    dimension 2; six agents measuring x, y or both (R = 1) at every tick."""
    agents = []
    for i in range(6):
        H = [[[1, 0, 0, 0]], [[0, 0, 1, 0]], [[1, 0, 0, 0], [0, 0, 1, 0]]][i % 3]
        agents.append(dict(id=i + 1, H=H, R=np.eye(len(H)).tolist(), sense="always", position=[0.0, 0.0]))
    raw = dict(
        name="constant-velocity", steps=200,
        model=dict(dynamics="matrix", A=[[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]],
                   G=[[0.5, 0], [1, 0], [0, 0.5], [0, 1]], Q=np.diag([1e-2, 1e-3, 1e-2, 1e-3]).tolist(),
                   x0=[0.0, 1.0, 0.0, 0.5], P0=np.diag([1.0, 0.1, 1.0, 0.1]).tolist(), position_dims=[0, 2]),
        topology=dict(kind=topology), agents=agents)
    return parse_scenario(raw)


def constant_acceleration(topology: str) -> Scenario:
    """n = 6 (x, vx, ax, y, vy, ay), one tick per step, a jerk input of
    dimension 2; six agents measuring x, y or both (R = 1) at every tick.
    C-DRKF and L-DRKF lose positive definiteness on it within 20 ticks in a
    ring, and DISKF's estimates pass 1e15 (the paper's algorithm: its
    compensation gain does not hold the unobserved acceleration back):
    each run says ``diverged``."""
    agents = []
    for i in range(6):
        H = [[[1, 0, 0, 0, 0, 0]], [[0, 0, 0, 1, 0, 0]], [[1, 0, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0]]][i % 3]
        agents.append(dict(id=i + 1, H=H, R=np.eye(len(H)).tolist(), sense="always", position=[0.0, 0.0]))
    axis = np.array([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    raw = dict(
        name="constant-acceleration", steps=200,
        model=dict(dynamics="matrix", A=np.kron(np.eye(2), axis).tolist(),
                   G=np.kron(np.eye(2), [[1 / 6], [0.5], [1.0]]).tolist(),
                   Q=np.kron(np.eye(2), np.diag([1e-2, 1e-3, 1e-4])).tolist(),
                   x0=[0.0, 1.0, 0.0, 0.0, 0.5, 0.0], P0=np.kron(np.eye(2), np.diag([1.0, 0.1, 0.01])).tolist(),
                   position_dims=[0, 3]),
        topology=dict(kind=topology), agents=agents)
    return parse_scenario(raw)


def three_d(base: Scenario) -> Scenario:
    """Scenario 1 with a third state component (a decaying altitude, also
    pushed by the input) and p_i = 2 sensors: (x, z) or (y, z)."""
    A = np.zeros((3, 3))
    A[:2, :2] = base.A
    A[2, 2] = 0.95
    agents = tuple(replace(a, H=np.array([[1.0, 0, 0], [0, 0, 1.0]]) if a.H[0, 0] else np.array([[0, 1.0, 0], [0, 0, 1.0]]),
                           R=2.0 * np.eye(2)) for a in base.agents)
    return replace(base, A=A, G=np.array([[1.0], [1.0], [0.5]]), Q=0.2 * np.eye(3), x0=np.array([200.0, 0.0, 0.0]),
                   P0=np.eye(3), agents=agents)


def two_sensors(base: Scenario) -> Scenario:
    """Every agent measures x and y (p_i = 2)."""
    return replace(base, agents=tuple(replace(a, H=np.eye(2), R=2.0 * np.eye(2)) for a in base.agents))


def mixed_sensors(base: Scenario) -> Scenario:
    """x, y, both (p = 2) and x + y: four sensor kinds."""
    Hs = [np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]), np.eye(2), np.array([[1.0, 1.0]])]
    Rs = [np.array([[2.0]]), np.array([[2.0]]), 2.0 * np.eye(2), np.array([[4.0]])]
    return replace(base, agents=tuple(replace(a, H=Hs[i % 4], R=Rs[i % 4]) for i, a in enumerate(base.agents)))


def scaled_R(base: Scenario, f: float) -> Scenario:
    return replace(base, agents=tuple(replace(a, R=f * a.R) for a in base.agents))


def cases() -> list[Case]:
    """Every case of the suite, in order."""
    out = []
    q, dyn = load_scenario("quadrants"), load_scenario("dynamic")
    for name, table in SHIPPED_INPUTS.items():
        for t, r in TOPOLOGIES_1:
            out.append(Case("inputs", f"S1 {_topo_label(t, r)}, {name}", _topo(_with_input(q, table), t, r)))
        for t, r in TOPOLOGIES_2:
            out.append(Case("inputs", f"S2 {_topo_label(t, r)}, {name}", _topo(_with_input(dyn, table), t, r)))
    for t, _ in TOPOLOGIES_1:
        cv = constant_velocity(t)
        for name, table in CV_INPUTS.items():
            out.append(Case("constant velocity", f"CV {t}, {name}", _with_input(cv, table)))
    variants = [("3-D state", "3-D", three_d(q)), ("p_i = 2", "p=2", two_sensors(q)),
                ("mixed sensors", "mixed", mixed_sensors(q))]
    variants += [("omega", f"ω={w:g}", replace(q, A=rotation(w))) for w in (0.05, 0.3, 0.6)]
    variants += [("R scale", f"R×{f:g}", scaled_R(q, f)) for f in (0.01, 100.0)]
    for group, tag, scn in variants:
        for name in VARIANT_INPUTS:
            for t, r in TOPOLOGIES_1:
                out.append(Case(group, f"{tag} {t}, {name}", _topo(_with_input(scn, SHIPPED_INPUTS[name]), t, r)))
    for N in (25, 50):
        rg = load_scenario("random-geometric", agents=N)
        for name in VARIANT_INPUTS:
            out.append(Case("random geometric", f"RG{N}, {name}", _with_input(rg, SHIPPED_INPUTS[name])))
    return out + grown_cases()


def grown_cases() -> list[Case]:
    """The families the suite grew by: the noise is not what the
    estimators are told (covariances x 10 and x 0.1, measurement and
    process; bursts of x 30), rare measurements, two input channels of
    different kinds, the constant-acceleration model."""
    out = []
    q, dyn = load_scenario("quadrants"), load_scenario("dynamic")
    for tag, world in WRONG_NOISE.items():
        for name in VARIANT_INPUTS:
            for t, r in TOPOLOGIES_1:
                out.append(Case("wrong noise", f"{tag} S1 {t}, {name}",
                                _topo(_with_input(q, SHIPPED_INPUTS[name]), t, r), world))
        if world.R != 1.0:
            for name in ("step", "zero"):
                out.append(Case("wrong noise", f"{tag} S2 range 120, {name}",
                                _topo(_with_input(dyn, SHIPPED_INPUTS[name]), "range", 120.0), world))
    for name in VARIANT_INPUTS:
        for t, r in TOPOLOGIES_1:
            out.append(Case("bursts", f"bursts S1 {t}, {name}", _topo(_with_input(q, SHIPPED_INPUTS[name]), t, r),
                            BURSTS))
    for name in ("step", "zero"):
        out.append(Case("bursts", f"bursts S2 range 120, {name}",
                        _topo(_with_input(dyn, SHIPPED_INPUTS[name]), "range", 120.0), BURSTS))
    for t, r in TOPOLOGIES_1:
        for name in ("step", "zero"):
            out.append(Case("rare measurement", f"rare S1 {t}, {name}", _topo(_with_input(q, SHIPPED_INPUTS[name]), t, r),
                            RARE))
        for name in ("zero", "steps 0.1"):
            out.append(Case("rare measurement", f"rare CV {t}, {name}",
                            _with_input(constant_velocity(t), CV_INPUTS[name]), RARE))
    two = replace(q, G=np.eye(2))
    for name, tables in CHANNEL_INPUTS.items():
        for t, r in TOPOLOGIES_1:
            out.append(Case("per-channel kinds", f"m=2 {t}, {name}",
                            _topo(replace(two, input=Channels(tuple(parse_input(x, 1) for x in tables))), t, r)))
    for t, _ in TOPOLOGIES_1:
        ca = constant_acceleration(t)
        for name, table in CA_INPUTS.items():
            out.append(Case("constant acceleration", f"CA {t}, {name}", _with_input(ca, table)))
    return out


def chi2_band(dof: int, seeds: int, p: float = 0.95):
    """The band of a NEES averaged over ``seeds`` runs of dimension ``dof``:
    [chi2_{S dof}((1-p)/2), chi2_{S dof}((1+p)/2)] / S, the quantiles by
    Wilson and Hilferty's approximation (within 0.1 % at S dof >= 20)."""
    k = dof * seeds
    z = 1.959963984540054 if p == 0.95 else float(np.sqrt(2) * _erfinv(p))
    q = lambda zz: k * (1 - 2 / (9 * k) + zz * math.sqrt(2 / (9 * k))) ** 3  # noqa: E731
    return q(-z) / seeds, q(z) / seeds


def _erfinv(y: float) -> float:  # pragma: no cover - only for p other than 0.95
    lo, hi = 0.0, 6.0
    for _ in range(80):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if math.erf(mid) < y else (lo, mid)
    return lo


def run_case(case: Case, seeds, steps: int | None = None, names=None) -> dict:
    """{estimator: row} for one case; a row holds mae_state, mae_input,
    nees (over the observed cells), nees_band_share, diverged and
    error_ratio (the largest state error over the target's farthest
    distance from the origin; NaN where the run diverged)."""
    scn, tr = case.simulate(seeds, steps)
    seen = observed(tr)
    return {name: case_row(tr, name, scn.params, seen) for name in names or algorithms.NAMES}


def case_row(tr, name: str, params: Params, seen: np.ndarray | None = None) -> dict:
    """One estimator's row on the trace ``tr`` (``run_case``); ``seen``:
    ``observed(tr)``, given when several rows share the trace."""
    seen = observed(tr) if seen is None else seen
    est = experiment.run_or_none(tr, name, params)
    if est is None:
        return dict(mae_state=float("nan"), mae_input=float("nan"), nees=float("nan"),
                    nees_band_share=float("nan"), diverged=True, error_ratio=float("nan"))
    e_state, e_in, nees = metrics.errors(tr, est)
    extent = float(np.linalg.norm(tr.truth_x[..., list(tr.position_dims)], axis=-1).max())
    band = chi2_band(tr.model.n, len(tr.seeds))
    s = metrics.summarize(e_state, e_in, nees)
    cell = nees.mean(axis=0)[seen.all(axis=0)]  # every seed's neighbourhood measured there
    return dict(mae_state=s["mae_state"], mae_input=s["mae_input"],
                nees=float(nees[seen].mean()) if seen.any() else float("nan"),
                nees_band_share=float(((cell >= band[0]) & (cell <= band[1])).mean()) if cell.size else float("nan"),
                diverged=False, error_ratio=float(e_state.max() / max(extent, np.finfo(float).tiny)))


def lowest(rows: dict) -> float:
    """The lowest state MAE of a case's rows ({estimator: row}) that did not
    diverge; NaN if every one did."""
    return min((v["mae_state"] for v in rows.values() if not v["diverged"]), default=math.nan)


def bank_members(scn: Scenario) -> list:
    """diskf-auto's first-order models on this scenario, each alone:
    [(model name, Params)], ``diskf-r`` with that input model
    (``input_models.default_bank``; ``diskf-r`` with one input model is
    ``diskf-auto`` with that model alone in its bank, the same input prior
    10^4 max(q_process, q_sensor)). The best of them on a case is what a
    choice of model that knew the case in advance reaches with these models.
    The oscillating models (a2 != 0) are not among them: ``diskf-r`` holds
    first-order input models only."""
    est = algorithms.get(AUTO)(scn.model(), scn.sensors(), scn.params)
    out = []
    for name, rho, a2, q in zip(est.bank, est.a1, est.a2, est.q):
        if a2 != 0:
            continue
        kind = "none" if q == 0 else "walk" if rho == 1 else "mean-reverting"
        robust = replace(scn.params.robust, input_model=kind, input_walk=float(q) if q > 0 else None,
                         input_rho=float(rho) if kind == "mean-reverting" else scn.params.robust.input_rho)
        out.append((name, replace(scn.params, robust=robust)))
    return out


def run_bank(case: Case, seeds, steps: int | None = None) -> dict:
    """{bank model: state MAE} on one case (``bank_members``), as ``run_case``
    measures it; NaN where the run diverged."""
    scn, tr = case.simulate(seeds, steps)
    seen = observed(tr)
    return {name: case_row(tr, "diskf-r", params, seen)["mae_state"] for name, params in bank_members(scn)}


SILENCES = ((0, 0), (1, 5), (6, 15), (16, math.inf))  # ticks since the agent's own last measurement


def ticks_since_measured(has: np.ndarray) -> np.ndarray:
    """(S, K, N) int: at each agent-tick, the ticks since the agent's own
    last measurement (0 where it measures; before its first, counted from
    tick 0)."""
    since = np.where(has, 0, 1)
    for k in range(1, since.shape[1]):
        since[:, k] = np.where(has[:, k], 0, since[:, k - 1] + 1)
    return since


def by_silence(case: Case, seeds, steps: int | None = None) -> dict:
    """{estimator or bank model: [state MAE over the agent-ticks whose own
    last measurement is 0, 1-5, 6-15, 16 or more ticks back]} on one case
    (``SILENCES``): ``diskf-auto`` and each model of its bank alone."""
    scn, tr = case.simulate(seeds, steps)
    since = ticks_since_measured(tr.has)
    out = {}
    for name, (alg, params) in [(AUTO, (AUTO, scn.params))] + [(m, ("diskf-r", p)) for m, p in bank_members(scn)]:
        with np.errstate(all="ignore"):
            e_state, _, _ = metrics.errors(tr, engine.run(tr, alg, params))
        out[name] = [float(e_state[(since >= lo) & (since <= hi)].mean()) for lo, hi in SILENCES]
    return out


def bank_summary(results: list[dict]) -> dict:
    """Over the results that hold a ``bank`` ({model: state MAE}, ``run(...,
    bank=True)``): per case where ``diskf-auto`` is not within 10 % of the
    case's best, the bank's best model alone and its ratio to that best;
    ``within`` counts those cases where it is within 10 %."""
    rows = []
    for r in results:
        mae = {k: v["mae_state"] for k, v in r["rows"].items() if not v["diverged"]}
        if AUTO not in mae or "bank" not in r:
            continue
        best = min(mae.values())
        if mae[AUTO] <= 1.10 * best:
            continue
        member = min((k for k, v in r["bank"].items() if math.isfinite(v)), key=r["bank"].get)
        rows.append(dict(case=r["case"], auto=mae[AUTO] / best, member=member, ratio=r["bank"][member] / best))
    return dict(auto_misses=len(rows), within=sum(x["ratio"] <= 1.10 for x in rows), rows=rows)


def targets(results: list[dict], seeds: int) -> dict:
    """The three targets over the suite's results [{case, n, rows}], and
    the runs that diverged or lost the target (``lost``), each named. A
    ``diskf-auto`` run that diverged misses its targets (and is counted in
    ``auto_diverged``)."""
    fam_ok = auto_ok = nees_ok = nees_cases = diverged = 0
    misses = {"family": [], "auto": [], "nees": [], "lost": [], "diverged": []}
    for r in results:
        rows = r["rows"]
        mae = {k: v["mae_state"] for k, v in rows.items() if not v["diverged"]}
        diverged += sum(v["diverged"] for v in rows.values())
        misses["diverged"] += [f"{r['case']}: {k}" for k, v in rows.items() if v["diverged"]]
        misses["lost"] += [f"{r['case']}: {k}" for k, v in rows.items() if lost(v)]
        if AUTO in rows and rows[AUTO]["diverged"]:
            misses["auto"].append(r["case"])
            misses["nees"].append(r["case"])
        fam = min((v for k, v in mae.items() if k.startswith(FAMILY_PREFIX)), default=math.inf)
        base = min((v for k, v in mae.items() if not k.startswith(FAMILY_PREFIX)), default=math.inf)
        if fam <= 1.01 * base:
            fam_ok += 1
        else:
            misses["family"].append(r["case"])
        if AUTO in mae:
            if mae[AUTO] <= 1.10 * min(mae.values()):
                auto_ok += 1
            else:
                misses["auto"].append(r["case"])
            lo, hi = chi2_band(r["n"], seeds)
            nees = rows[AUTO]["nees"]
            if math.isfinite(nees):
                nees_cases += 1
                if lo <= nees <= hi:
                    nees_ok += 1
                else:
                    misses["nees"].append(r["case"])
    n = len(results)
    auto_diverged = sum(1 for r in results if AUTO in r["rows"] and r["rows"][AUTO]["diverged"])
    return dict(cases=n, family_within_1pct=fam_ok, auto_within_10pct=auto_ok, auto_nees_in_band=nees_ok,
                auto_nees_cases=nees_cases + auto_diverged, diverged_runs=diverged, auto_diverged=auto_diverged,
                lost_runs=len(misses["lost"]), misses=misses)


def lost(row: dict) -> bool:
    """Whether a run that did not diverge lost the target (``FAR``); a row
    stored without ``error_ratio`` did not."""
    return not row["diverged"] and row.get("error_ratio", 0.0) > FAR


def selected(select=None) -> list[Case]:
    """The cases whose label contains ``select`` (or any of a list of
    them), or whose group it names; every case for None."""
    sel = None if select is None else [select] if isinstance(select, str) else list(select)
    return [c for c in cases() if sel is None or any(s in c.label or s == c.group for s in sel)]


def run(seeds: int = 20, steps: int | None = None, names=None, select=None, progress=True, bank=False,
        first: int = 0, jobs: int = 1, noise_level: float = 0.0, evidence_dof: float = 0.0,
        noise_span: float = 0.0) -> dict:
    """The whole suite (or the cases ``selected(select)``) on seeds
    ``first`` .. ``first + seeds - 1``; ``names``: only these estimators;
    ``bank``: each result also holds ``run_bank``'s ``bank``; ``jobs``:
    the cases in that many processes (the same rows, in the same order);
    ``noise_level``, ``evidence_dof``, ``noise_span``: ``[estimator.auto]``'s,
    set on every case (``with_auto``; 0: as the case has it)."""
    all_cases = [with_auto(c, noise_level=noise_level, evidence_dof=evidence_dof, noise_span=noise_span)
                 for c in selected(select)]
    t0 = time.monotonic()
    work = [(c, seeds, steps, names, first, bank) for c in all_cases]

    def shown(i, record):
        if progress:
            rows = record["rows"]
            if len(rows) <= 3:  # a few estimators (--estimators): each one's
                what = ", ".join(f"{k} {v['mae_state']:.3g}" for k, v in rows.items())
            else:
                what = f"best {lowest(rows):.3g}, {AUTO} {rows.get(AUTO, {}).get('mae_state', math.nan):.3g}"
            print(f"[{i}/{len(all_cases)} {time.monotonic() - t0:6.0f} s] {record['case']}: {what}",
                  file=sys.stderr, flush=True)
        return record

    if jobs <= 1 or len(work) <= 1:
        results = [shown(i, _case_job(w)) for i, w in enumerate(work, 1)]
    else:
        from diskf_mesh.studies.pool import process_pool

        with process_pool(min(jobs, len(work))) as pool:
            results = [shown(i, r) for i, r in enumerate(pool.map(_case_job, work), 1)]
    return document(results, seeds, steps, first)


def with_auto(case: Case, **fields) -> Case:
    """``case`` with the ``[estimator.auto]`` fields given and not 0 set;
    ``noise_level`` only where it has one input channel (the level needs
    one bank)."""
    scn = case.scenario
    fields = {k: v for k, v in fields.items() if v and not (k == "noise_level" and scn.G.shape[1] > 1)}
    if not fields:
        return case
    return replace(case, scenario=scn.with_overrides(params=scn.params.with_setting("auto", **fields)))


def _case_job(job: tuple) -> dict:
    """One case's record for ``run`` (a top-level function: a worker
    process can run it)."""
    c, seeds, steps, names, first, bank = job
    record = case_record(c, seeds, steps, names, first)
    if bank:
        record["bank"] = run_bank(c, range(first, first + seeds), steps)
    return record


class Mismatch(ValueError):
    """A stored held-out document that cannot stand beside a new run."""


REPORT_KEY = "heldout"  # the held-out document's entry in a report's results.json


def stored(path) -> dict:
    """The held-out document in ``path``: what ``--json`` writes, or the
    ``REPORT_KEY`` entry of a report's ``results.json``; its missing
    numbers read as NaN (``nan_rows``). ``Mismatch`` if it is neither."""
    try:
        with open(path) as f:
            doc = json.load(f)
    except OSError as e:
        raise Mismatch(e.strerror or str(e)) from None
    except ValueError as e:
        raise Mismatch(f"not JSON ({e})") from None
    if isinstance(doc, dict) and "results" not in doc and isinstance(doc.get(REPORT_KEY), dict):
        doc = doc[REPORT_KEY]
    if not (isinstance(doc, dict) and isinstance(doc.get("results"), list) and "seeds" in doc):
        raise Mismatch("not a held-out document (no 'seeds' and 'results')")
    return nan_rows(doc)


def nan_rows(doc: dict) -> dict:
    """A held-out document read back from JSON: its missing numbers (null,
    as JSON writes NaN: the input MAE of an estimator of no input) as NaN."""
    for r in doc.get("results", []):
        for row in r["rows"].values():
            for k, v in row.items():
                if v is None:
                    row[k] = math.nan
    return doc


def comparable(old: dict, labels, seeds: int, steps: int | None, first: int) -> None:
    """``Mismatch`` (naming what differs) unless the stored document ``old``
    is of these seeds, first seed and ticks and holds every case of
    ``labels``."""
    for key, default, value in (("seeds", None, seeds), ("first_seed", 0, first), ("steps", None, steps)):
        if old.get(key, default) != value:
            raise Mismatch(f"the stored document has {key} = {old.get(key, default)}, this run {value}: "
                           "run with the same --seeds, --first-seed and --ticks")
    have = {r.get("case") for r in old["results"]}
    missing = [label for label in labels if label not in have]
    if missing:
        raise Mismatch(f"the stored document has no case {missing[0]!r}")


def merge(new: dict, old: dict) -> dict:
    """``new``'s rows beside ``old``'s for every estimator ``new`` did not
    run, case by case; the targets computed again over the merged rows.
    ``old`` must be ``comparable`` with ``new``."""
    comparable(old, [r["case"] for r in new["results"]], new["seeds"], new.get("steps"), new.get("first_seed", 0))
    by_case = {r["case"]: r for r in old["results"]}
    results = []
    for r in new["results"]:
        rows = {k: r["rows"].get(k, v) for k, v in by_case[r["case"]]["rows"].items()}  # the stored columns' order
        rows.update(r["rows"])
        results.append({**r, "rows": rows})
    return document(results, new["seeds"], new.get("steps"), new.get("first_seed", 0))


def case_record(case: Case, seeds: int, steps: int | None = None, names=None, first: int = 0) -> dict:
    """One case's result in the suite's document: {case, group, n, rows}
    (``run_case`` on seeds first .. first + seeds - 1)."""
    return dict(case=case.label, group=case.group, n=case.scenario.G.shape[0],
                rows=run_case(case, range(first, first + seeds), steps, names))


def document(results: list[dict], seeds: int, steps: int | None = None, first: int = 0) -> dict:
    """The suite's document from its cases' records: {seeds, first_seed, steps, results, targets}."""
    return dict(seeds=seeds, first_seed=first, steps=steps, results=results, targets=targets(results, seeds))


HEADER = (
    "# Held-out suite: every estimator on inputs, models and networks beyond the shipped cases\n\n"
    "Generated by `python -m diskf_mesh.studies.heldout --seeds 20 --markdown docs/heldout.md` "
    "(`diskf_mesh/studies/heldout.py`; the cases are listed there). Bold: the lowest state MAE of the case. "
    "NEES: the mean over the (tick, agent) cells whose neighbourhood measures / the share of the cells where every "
    "seed's neighbourhood measures whose NEES averaged over the seeds lies in the χ² 95 % band of that average. "
    "`diskf-auto`'s chain switch probability was compared at 0.01, 0.001 and 0.0001 on these cases and set to "
    "0.001, and its oscillating models' radius at 0.95 and e^(-1/10) and set to 0.95 (docs/estimators.md); their "
    "periods (4 to 32 ticks) are fixed, and every other default follows the scenario's scales. The grown families "
    "(a world whose noise is not what the estimators are told, bursts, rare measurement, two input channels of "
    "different kinds, the constant-acceleration model: `grown_cases`) were added after those defaults, and no "
    "default was changed on them. The constants of the noise `diskf-auto` learns with `[estimator.auto] noise = "
    "true` (`core.noise`, off by default: log r moves 0.2 a measured tick, times the square root of r's share "
    "of the innovation covariance, on the difference between this tick's innovation and the last measured "
    "tick's, scored against the bank's predicted mean; r from 0.01 to 1000) were chosen on seeds 0..9 of ten "
    "cases (Scenario 1 in a ring with the random steps, the series and the fast sine; Scenario 1 all-to-all "
    "and Scenario 2 all-to-all with the fast sine; Scenario 2 all-to-all with the random telegraph; R × 10 in "
    "a ring with no input and in Scenario 2 at range 120 with the step; bursts in a ring with no input; R × "
    "0.1 in a ring with the step) among the steps 0.1, 0.15, 0.2 and 0.3, the innovation's level or its "
    "difference, scored against the agent's own prediction with the input it last fused, with the input the "
    "bank predicts, or the bank's predicted mean, a majority of the last 7 or 9 ticks' signs, and a step "
    "decaying from 0.5 or 1 as 1/√(1 + n) (the share's power 0.5 and no Student-t weight were chosen before on "
    "seven of these cases among the powers 0, 0.5 and 1, with and without the weight); the seeds no constant "
    "was chosen on are 20..39 "
    "(`--first-seed 20`). That a neighbourhood which measured keeps its own model probabilities, and pools its senders' only "
    "where it measured nothing, was chosen on seeds 0..9 of eight cases (the constant-acceleration ring with no "
    "input and with the white jerk; Scenario 1 in a ring with the random steps; rare measurement with the step, "
    "all-to-all and ring; two channels, the step and white noise, in a ring; the random geometric network of 25 "
    "with the step; Scenario 2 at range 120 with the step). That the state's output mixture leaves out the "
    "models whose probability is under the mixing's prune, 10⁻³ (`input_models.output_weights`; the input's "
    "mixes every model), was chosen on seeds 0..9 of the twelve constant-acceleration cases and checked on "
    "seeds 0..9 of the 148 cases before the grown families. The random walks' hand-down (`[estimator.auto] "
    "hand_down`, `input_models.hand_down`: each walk moves to each walk of a smaller scale with 0.001 a tick) was "
    "chosen on seeds 0..19: 0.003 both ways and 0.001 downwards on the 235 cases, and 0.001, 0.003 and 0.01 "
    "downwards on three (Scenario 1 isolated with the step and with the constant 5, rare measurement all-to-all "
    "with the step); the seeds no constant was chosen on are 20..39 (docs/estimators.md gives both). A bank "
    "per input channel (`[estimator.auto] per_channel`, on; the models of the other channels held at their "
    "banks' most probable, a bank the tick told less than 10⁻³ of log-likelihood following the informed "
    "banks, the relayed inputs on each bank's own channel) was chosen on seeds 0..19 of the two-channel, "
    "constant-velocity and constant-acceleration cases (against one shared bank, the relay left out, and the "
    "banks' probabilities pooled half with each other's); the seeds "
    "no choice was made on are 20..39.")


def markdown(doc: dict, header: bool = True) -> str:
    """The suite as tables: the targets, then every case x estimator; the
    page's ``HEADER`` first unless ``header`` is false (a section of another
    page)."""
    res = doc["results"]
    names = list(res[0]["rows"]) if res else []
    t = targets(res, doc["seeds"])  # from the rows (a stored document's may predate a count)
    n = t["cases"]
    pct = lambda a, b: f"{a} of {b} ({100 * a / max(b, 1):.0f} %)"  # noqa: E731
    first = doc.get("first_seed", 0)
    lines = [f"Seeds {first}..{first + doc['seeds'] - 1}, {doc['steps'] or 'the scenario’s'} ticks, {n} cases.", "",
             "| target | reached |", "|---|---|",
             f"| DISKF family’s best within 1 % of the best baseline (≥ 95 %) | {pct(t['family_within_1pct'], n)} |",
             f"| `{AUTO}` within 10 % of the case’s best (≥ 90 %) | {pct(t['auto_within_10pct'], n)} |",
             f"| `{AUTO}` mean NEES in the χ² 95 % band (≥ 90 %) | {pct(t['auto_nees_in_band'], t['auto_nees_cases'])} |",
             f"| runs whose covariance diverged | {t['diverged_runs']} |",
             f"| runs of `{AUTO}` whose covariance diverged (0) | {t['auto_diverged']} |",
             f"| runs that lost the target (a state error beyond {FAR:g} × the target’s farthest distance from the "
             f"origin) | {t.get('lost_runs', 0)} |", ""]
    for what, key, fmt in (("State MAE", "mae_state", "{:.3g}"), ("Input MAE", "mae_input", "{:.3g}"),
                           ("NEES (observed cells) / share of cells in band", "nees", None)):
        lines += [f"### {what}", "", "| case | " + " | ".join(algorithms.label(k) for k in names) + " |",
                  "|---|" + "---|" * len(names)]
        for r in res:
            rows = r["rows"]
            best = lowest(rows)
            cells = []
            for k in names:
                v = rows[k]
                if v["diverged"]:
                    cells.append("diverged")
                elif fmt is None:
                    cells.append(f"{v['nees']:.2g} / {100 * v['nees_band_share']:.0f} %"
                                 if math.isfinite(v["nees_band_share"]) else f"{v['nees']:.2g}")
                else:
                    s = fmt.format(v[key]) if math.isfinite(v[key]) else "–"
                    cells.append(f"**{s}**" if key == "mae_state" and v[key] == best else s)
            lines.append(f"| {r['case']} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(([HEADER, ""] if header else []) + lines)


FAMILIES = (("no input", ("none",)), ("random walk", ("walk",)),
            ("zero-mean / mean-reverting", ("zero-mean", "reverting")), ("oscillating", ("oscillating",)))


def model_choice(scn: Scenario, seed: int = 0, agent: int = 0):
    """diskf-auto's model probabilities over time for one agent of one seed,
    summed by family (``FAMILIES``): (ticks (K,), {family: (K,)}, input (K,)),
    the engine's own tick loop (dense links) with the state read out."""
    tr = simulate(scn, [seed])
    est = algorithms.get(AUTO)(tr.model, tr.sensors, scn.params)
    K, N = tr.has.shape[1:]
    state = est.init((1, N))
    mu = np.empty((K, len(est.bank)))
    for k in range(1, K + 1):
        state, msg = est.local(state, k, tr.y[:, k - 1], tr.has[:, k - 1])
        state, _ = engine.DenseLinks(tr.links[:, k - 1], 1).fuse(est, state, msg, None)
        mu[k - 1] = state.mu[0, agent]
    fam = {name: mu[:, [i for i, b in enumerate(est.bank) if b.split()[0] in keys]].sum(axis=1)
           for name, keys in FAMILIES}
    return np.arange(1, K + 1), fam, tr.truth_d[0, :, 0]


def choice_figure(path, seed: int = 0) -> None:
    """One figure: diskf-auto's model probabilities (agent 1, by family) over
    time on Scenario 1 in a ring, for three inputs: the shipped step, no
    input, and a sine of period 10."""
    from matplotlib.figure import Figure
    q = load_scenario("quadrants").with_overrides(topology="ring")
    fig = Figure(figsize=(10, 6.5), constrained_layout=True)
    axes = fig.subplots(3, 1, sharex=True)
    for ax, name in zip(axes, ("step", "zero", "sine fast")):
        t, fam, d = model_choice(_with_input(q, SHIPPED_INPUTS[name]), seed)
        ax.stackplot(t, *fam.values(), labels=list(fam), alpha=0.8)
        ax.set_ylabel("probability")
        ax.set_ylim(0, 1)
        tw = ax.twinx()
        tw.plot(t, d, color="k", lw=1, label="true input")
        tw.set_ylabel("input d")
        ax.set_title(f"Scenario 1, ring, input: {name}; agent 1, seed {seed}")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("tick")
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m diskf_mesh.studies.heldout", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0,
                    help="the first seed (default 0): a check on seeds no default was chosen on, e.g. 100")
    add_ticks(ap, type=int, default=None, help="horizon in ticks (default: each case's)")
    ap.add_argument("--select", default=None, action="append",
                    help="only the cases whose label contains this (or a group name); may be repeated")
    ap.add_argument("--estimators", default=None, metavar="A,B",
                    help="only these estimators (comma-separated; default: every one)")
    ap.add_argument("--against", default=None, metavar="FILE",
                    help="take the other estimators' rows from this held-out document (--json's, or a report's "
                         "results.json) of the same seeds and ticks")
    ap.add_argument("--jobs", type=int, default=1, help="run the cases in this many processes (default 1)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--markdown", default=None)
    ap.add_argument("--figure", default=None, help="also draw diskf-auto's model choice over time (a PNG)")
    ap.add_argument("--bank", action="store_true",
                    help="also run each model of diskf-auto's bank alone; print, per case diskf-auto misses by more "
                         "than 10 %%, the best of them")
    ap.add_argument("--noise-level", type=float, default=0.0, metavar="X",
                    help="run diskf-auto with [estimator.auto] noise_level = X on every case of one input channel")
    ap.add_argument("--evidence-dof", type=float, default=0.0, metavar="NU",
                    help="run diskf-auto with [estimator.auto] evidence_dof = NU (a Student-t's evidence) on every case")
    ap.add_argument("--noise-span", type=float, default=0.0, metavar="S",
                    help="run diskf-auto with [estimator.auto] noise_span = S (the noise weighed at R, sqrt(S) R and S R) "
                         "on every case")
    ap.add_argument("--by-silence", metavar="CASE", default=None,
                    help="only this case (its label): the state MAE of diskf-auto and of each bank model alone, by "
                         "ticks since the agent's own last measurement")
    a = ap.parse_args(argv)
    if a.seeds < 1 or (a.ticks is not None and a.ticks < 1):
        print("error: --seeds and --ticks must be at least 1", file=sys.stderr)
        return 2
    if a.first_seed < 0:
        print("error: --first-seed must be at least 0", file=sys.stderr)
        return 2
    if a.jobs < 1:
        print("error: --jobs must be at least 1", file=sys.stderr)
        return 2
    try:
        names = None if a.estimators is None else algorithms.parse_list(a.estimators)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    old = None
    if a.against is not None:  # before anything runs: a mismatch of seeds, ticks or cases costs nothing
        labels = [c.label for c in selected(a.select)]
        try:
            if not labels:
                raise Mismatch("--select matches no case")
            old = stored(a.against)
            comparable(old, labels, a.seeds, a.ticks, a.first_seed)
        except Mismatch as e:
            print(f"error: --against {a.against}: {e}", file=sys.stderr)
            return 2
    seeds = range(a.first_seed, a.first_seed + a.seeds)
    if a.by_silence is not None:
        found = [c for c in cases() if c.label == a.by_silence]
        if not found:
            print(f"error: --by-silence: no case {a.by_silence!r} (the labels are in docs/heldout.md)", file=sys.stderr)
            return 2
        heads = [f"{lo}" if lo == hi else f"{lo}-{hi}" if hi < math.inf else f"{lo}+" for lo, hi in SILENCES]
        print(f"{a.by_silence}, seeds {seeds[0]}..{seeds[-1]}: state MAE by ticks since the agent's own last "
              "measurement")
        print("| estimator | " + " | ".join(heads) + " |")
        print("|---|" + "---:|" * len(heads))
        for name, v in by_silence(found[0], seeds, a.ticks).items():
            print(f"| {name} | " + " | ".join(f"{x:.1f}" for x in v) + " |")
        return 0
    if a.figure:
        choice_figure(a.figure)
    try:
        AutoOptions(noise_level=a.noise_level, evidence_dof=a.evidence_dof, noise_span=a.noise_span)
    except ValueError as e:  # "auto.<field>: <message>": named by its flag
        field, _, msg = str(e).partition(": ")
        print(f"error: --{field.rpartition('.')[2].replace('_', '-')}: {msg}", file=sys.stderr)
        return 2
    doc = run(a.seeds, a.ticks, names=names, select=a.select, bank=a.bank, first=a.first_seed, jobs=a.jobs,
              noise_level=a.noise_level, evidence_dof=a.evidence_dof, noise_span=a.noise_span)
    if old is not None:
        doc = merge(doc, old)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(doc, f, indent=1, default=float)
    text = markdown(doc)
    if a.markdown:
        with open(a.markdown, "w") as f:
            f.write(text + "\n")
    t = doc["targets"]
    if names is not None and old is None:
        print("note: --estimators without --against: the targets compare the estimators run, not every one",
              file=sys.stderr)
    print(json.dumps({k: v for k, v in t.items() if k != "misses"}))
    for k, v in t["misses"].items():
        print(f"misses ({k}): {'; '.join(v)}")
    if a.bank:
        b = bank_summary(doc["results"])
        print(f"bank: one model alone within 10 % of the case's best in {b['within']} of the {b['auto_misses']} "
              f"cases {AUTO} misses")
        for x in b["rows"]:
            print(f"  {x['case']}: {AUTO} {x['auto']:.2f} x the best, {x['member']} alone {x['ratio']:.2f} x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
