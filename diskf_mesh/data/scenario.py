"""Scenarios: TOML files describing the world, and their simulation.

A scenario is a TOML file (shipped ones live in ``diskf_mesh/scenarios``;
users pass a path to their own). ``load_scenario`` parses and validates it
into a ``Scenario``; ``simulate`` draws ground truth and measurements for a
batch of seeds into a ``Trace`` (see ``diskf_mesh.data.trace``).

Format (see ``scenarios/quadrants.toml`` for a commented example):

    name, description, steps
    [model]     dynamics = "rotation" (omega, rad/tick) | "matrix" (A)
                G, Q, x0, P0, position_dims
    [input]     kind = "step" | "constant" | "sine" | "ramp" | "steps" |
                "telegraph" | "white" | "series" (``data.inputs``)
    [estimator] the estimators' settings (``estimators.Params``: each
                estimator declares its own, e.g. window, eps, consensus_eps;
                a dataclass-valued one is a sub-table, [estimator.robust])
    [topology]  kind = "all" | "ring" | "none" | "range"; range
    [[agents]]  id, H, R, sense = "quadrant" | "always" | "range" (sense_range)
                position = [x, y]                     a static agent, or
                path = [[x, y], ...], period = ticks  a closed piecewise-linear
                                                      loop, start phase ``phase``
    [generate]  kind = "random-geometric": agents are generated instead of
                listed (agents, box, sense_range, layout_seed)
"""
from __future__ import annotations

import difflib
import functools
import tomllib
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path

import numpy as np

from diskf_mesh.core.errors import InputError
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.lies import Lie, resolve
from diskf_mesh.data.inputs import InputSpec, parse_input
from diskf_mesh.core.model import LinearModel, Sensors
from diskf_mesh.estimators import REGISTRY, SETTINGS, Params
from diskf_mesh.data.trace import Trace
from diskf_mesh.data.validate import (agent_id, check_keys, index_list, internal_ids, matrix, scalar, setting, spd,
                                      unique_ids, vector)

TOPOLOGIES = ("all", "ring", "none", "range")
SENSE_KINDS = ("quadrant", "always", "range")


@dataclass(frozen=True)
class AgentSpec:
    id: int                                 # the run's integer id (validate.internal_ids)
    H: np.ndarray
    R: np.ndarray
    sense: str = "quadrant"
    sense_range: float = np.inf
    position: np.ndarray | None = None      # static
    path: np.ndarray | None = None          # (W, 2) closed loop
    period: float = 1.0
    phase: float = 0.0
    label: int | str | None = None          # the id the scenario gave ("drone-1"); None: ``id``

    @property
    def name(self) -> int | str:
        """The agent's id as the user knows it (results, recordings, views)."""
        return self.id if self.label is None else self.label

    @property
    def mobile(self) -> bool:
        return self.path is not None

    def position_at(self, ticks: np.ndarray) -> np.ndarray:
        """Position (len(ticks), 2) at the given ticks."""
        ticks = np.asarray(ticks, dtype=float)
        if self.path is None:
            return np.broadcast_to(self.position, ticks.shape + (2,)).copy()
        pts = np.vstack([self.path, self.path[:1]])
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        s = ((ticks / self.period + self.phase) % 1.0) * cum[-1]
        return np.stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])], axis=-1)


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    steps: int
    A: np.ndarray            # (n, n) constant, or (K, n, n)
    G: np.ndarray
    Q: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    position_dims: tuple
    input: InputSpec
    params: Params
    topology: str
    comm_range: float
    agents: tuple
    faults: dict = field(default_factory=dict)
    lies: tuple = ()         # ``data.lies.Lie``s, each agent the run's id (the fault plan's [[faults.lies]])

    @property
    def N(self) -> int:
        return len(self.agents)

    @property
    def labels(self) -> tuple:
        """Every agent's id as the scenario gave it, in order."""
        return tuple(a.name for a in self.agents)

    @functools.cached_property
    def ids(self) -> tuple:
        """Every agent's id, in order."""
        return tuple(a.id for a in self.agents)

    @functools.cached_property
    def id_set(self) -> frozenset:
        """The same ids, as a set."""
        return frozenset(self.ids)

    def index(self, agent_id) -> int:
        """The place of agent ``agent_id`` in ``ids``."""
        return self.places[agent_id]

    @functools.cached_property
    def places(self) -> dict:
        """Every agent id -> its place in ``ids`` (one dict, shared by whoever looks)."""
        return {j: i for i, j in enumerate(self.ids)}

    def sensors(self) -> Sensors:
        """Every agent's sensor (made once; read-only arrays)."""
        return self._sensors

    @functools.cached_property
    def _sensors(self) -> Sensors:
        s = Sensors.from_list(self.ids, [a.H for a in self.agents], [a.R for a in self.agents])
        for a in (s.H, s.R, s.p):
            a.flags.writeable = False
        return s

    def model(self, steps: int | None = None) -> LinearModel:
        K = steps or self.steps
        A = self.A if self.A.ndim == 3 else np.broadcast_to(self.A, (K,) + self.A.shape)
        if A.shape[0] < K:
            raise InputError("steps", f"the scenario's A sequence has {A.shape[0]} entries, {K} requested")
        return LinearModel(np.ascontiguousarray(A[:K]), self.G, self.Q, self.x0, self.P0)

    def inputs(self, steps: int, seed: int = 0) -> np.ndarray:
        """d_k for k = 0..steps-1 (d[k] acts between tick k and k+1) under
        simulation seed ``seed`` (``data.inputs``: its seed rule)."""
        return self.input.values(steps, seed)

    def positions(self, steps: int) -> np.ndarray:
        """Agent positions (steps, N, 2) at ticks 1..steps."""
        return self.positions_at(np.arange(1, steps + 1))

    def positions_at(self, ticks) -> np.ndarray:
        """Agent positions (len(ticks), N, 2) at the given ticks."""
        return np.stack([a.position_at(ticks) for a in self.agents], axis=1)

    def check_size(self, seeds: int = 1, steps: int | None = None) -> None:
        """``InputError`` if simulating ``seeds`` seeds would need more than
        ``MEMORY_BOUND`` bytes (``simulation_bytes``)."""
        n, m = self.G.shape
        moving = self.topology == "range" and any(a.mobile for a in self.agents)
        size = (self.N, steps or self.steps, n, max(a.H.shape[0] for a in self.agents), m, seeds, moving)
        # the worst case, every agent hearing every other, when it fits; else the largest neighbourhood counted
        degree = None if simulation_bytes(*size) <= MEMORY_BOUND else self.largest_neighbourhood(size[1])
        check_size(*size, degree=degree)

    def largest_neighbourhood(self, steps: int) -> int:
        """The most agents one agent hears, itself included, at any of
        ticks 1..steps (about: range links are counted on a k-d tree, whose
        distances may round differently at the range itself)."""
        N = self.N
        if self.topology == "range" and np.isfinite(self.comm_range):
            from scipy.spatial import cKDTree  # only for a network too large for the worst case: 0.3 s to import

            moving = any(a.mobile for a in self.agents)
            return max(int(cKDTree(pos).query_ball_point(pos, self.comm_range, return_length=True).max())
                       for pos in self.positions(steps if moving else 1))
        return {"ring": min(N, 3), "none": 1}.get(self.topology, N)

    def with_overrides(self, topology=None, comm_range=None, steps=None, params=None) -> "Scenario":
        out = self
        if topology is not None:
            if topology not in TOPOLOGIES:
                raise InputError("topology", f"must be one of {', '.join(TOPOLOGIES)}, got {topology!r}")
            out = replace(out, topology=topology)
        if comm_range is not None:
            comm_range = scalar(comm_range, "range", float, low=0.0, allow_inf=True)
            out = replace(out, comm_range=comm_range, topology="range" if topology is None else out.topology)
        if steps is not None:
            out = replace(out, steps=scalar(steps, "steps", int, low=1))
        if params is not None:
            out = replace(out, params=params)
        return out

    def with_lies(self, lies) -> "Scenario":
        """This scenario with these lies (``data.lies.Lie``, agents as the
        scenario names them) instead of its own."""
        return replace(self, lies=resolve(lies, self.labels, [a.id for a in self.agents]))


# --------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------
def shipped_scenarios() -> list[str]:
    root = resources.files("diskf_mesh") / "scenarios"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def scenario_path(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.is_dir():
        raise InputError("scenario", f"{name_or_path} is a folder; give a scenario's .toml file or a shipped name "
                                     f"({', '.join(shipped_scenarios())})")
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise InputError("scenario", f"no such file: {name_or_path}")
        return p
    root = resources.files("diskf_mesh") / "scenarios" / f"{name_or_path}.toml"
    if not root.is_file():
        shipped = shipped_scenarios()
        close = difflib.get_close_matches(str(name_or_path), shipped, n=1, cutoff=0.6)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise InputError("scenario", f"unknown scenario {name_or_path!r}; {hint}shipped: {', '.join(shipped)}, "
                                     "or give a .toml path")
    return Path(str(root))


def load_scenario(name_or_path: str, agents: int | None = None) -> Scenario:
    """Load and validate a scenario by shipped name or path.

    ``agents`` overrides the agent count of a generated scenario."""
    path = scenario_path(name_or_path)
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise InputError("scenario", f"cannot read {path}: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError("scenario", f"{path} is not valid TOML: {e}") from None
    return parse_scenario(raw, agents=agents, base=path.parent)


TOP_KEYS = ("name", "description", "steps", "model", "input", "estimator", "topology", "agents", "generate", "faults")
MODEL_KEYS = {"rotation": ("dynamics", "omega", "G", "Q", "x0", "P0", "position_dims"),
              "matrix": ("dynamics", "A", "G", "Q", "x0", "P0", "position_dims")}
TOPOLOGY_KEYS = ("kind", "range")
AGENT_KEYS = ("id", "H", "R", "sense", "sense_range", "position", "path", "period", "phase")
GENERATE_KEYS = ("kind", "agents", "box", "sense_range", "R", "layout_seed")


def parse_scenario(raw: dict, agents: int | None = None, base: Path | None = None) -> Scenario:
    """A ``Scenario`` from a parsed TOML document; every field is typed and
    range-checked (``validate.setting``), unknown keys are errors. ``base``:
    the folder a relative ``[input] file`` is read from."""
    check_keys(raw, TOP_KEYS, "")
    steps = setting(raw, "steps", "", int, 200, low=1)
    mdl = raw.get("model", {})
    dyn = setting(check_keys(mdl, MODEL_KEYS["matrix"] + ("omega",), "model"), "dynamics", "model", str, "matrix",
                  choices=tuple(MODEL_KEYS))
    for key in set(mdl) - set(MODEL_KEYS[dyn]):
        raise InputError(f"model.{key}", f"is not used with dynamics = {dyn!r}")
    G = matrix(mdl.get("G"), "model.G")
    n, m = G.shape
    if n == 0 or m == 0:
        raise InputError("model.G", f"must be n x m with n, m >= 1, got {n}x{m}")
    if dyn == "rotation":
        if n != 2:
            raise InputError("model.dynamics", "rotation needs a 2-dimensional state")
        w = setting(mdl, "omega", "model", float, 0.0)
        A = np.array([[np.cos(w), -np.sin(w)], [np.sin(w), np.cos(w)]])
    else:
        A = matrix(mdl.get("A"), "model.A", (n, n))
    Q = spd(matrix(mdl.get("Q"), "model.Q", (n, n)), "model.Q")
    P0 = spd(matrix(mdl.get("P0"), "model.P0", (n, n)), "model.P0")
    x0 = vector(mdl.get("x0"), "model.x0", n)
    # the target's position is compared with the agents' 2-D positions
    pos_dims = index_list(mdl.get("position_dims", list(range(min(n, 2)))), "model.position_dims", n, max_len=2)

    input_spec = parse_input(raw.get("input", {}), m, base)

    params = _parse_estimator(raw.get("estimator", {}))

    topo = check_keys(raw.get("topology", {}), TOPOLOGY_KEYS, "topology")
    topology = setting(topo, "kind", "topology", str, "all", choices=TOPOLOGIES)
    comm_range = setting(topo, "range", "topology", float, np.inf, low=0.0, allow_inf=True)

    gen = raw.get("generate")
    if gen is not None:
        if "agents" in raw:
            raise InputError("agents", "give either [[agents]] or [generate], not both")
        specs = _generate_agents(gen, n, agents, steps)
    else:
        if agents is not None:
            raise InputError("agents", "--agents applies only to generated scenarios (random-geometric)")
        listed = raw.get("agents", [])
        if not isinstance(listed, list):
            raise InputError("agents", "must be a list of tables ([[agents]])")
        specs = tuple(_parse_agent(a, i, n) for i, a in enumerate(listed))
    if not specs:
        raise InputError("agents", "a scenario needs at least one agent")
    labels = unique_ids([a.name for a in specs], "agents.id")
    specs = tuple(replace(a, id=i) for a, i in zip(specs, internal_ids(labels)))

    faults = dict(raw.get("faults", {})) if isinstance(raw.get("faults", {}), dict) else raw.get("faults")
    told = faults.pop("lies", []) if isinstance(faults, dict) else []
    if not isinstance(told, list):
        raise InputError("faults.lies", "must be a list of tables ([[faults.lies]])")
    faults = check_keys(faults, [f.name for f in fields(FaultConfig)], "faults")
    FaultConfig.from_mapping(faults)
    lies = resolve([Lie.from_mapping(t, f"faults.lies[{i}]") for i, t in enumerate(told)], labels,
                   [a.id for a in specs])
    sensors = Sensors.from_list([a.id for a in specs], [a.H for a in specs], [a.R for a in specs])
    for cls in REGISTRY.values():  # a setting an estimator refuses for this model and these sensors
        refused = cls.refuse(params, LinearModel(A[None] if A.ndim == 2 else A, G, Q, x0, P0), sensors)
        if refused:
            raise InputError(*refused)
    return Scenario(
        name=setting(raw, "name", "", str, "custom"),
        description=setting(raw, "description", "", str, ""),
        steps=steps, A=A, G=G, Q=Q, x0=x0, P0=P0, position_dims=pos_dims,
        input=input_spec,
        params=params, topology=topology, comm_range=comm_range,
        agents=specs, faults=dict(faults), lies=lies,
    )


def _parse_estimator(est) -> Params:
    """``Params`` from an ``[estimator]`` table: its keys are the settings
    the registered estimators declare (``estimators.SETTINGS``), each read
    by its declared kind and checks; ``"none"`` (or -1) is None where a
    setting is optional; a setting whose kind is a dataclass of switches is
    a sub-table (``[estimator.robust]``)."""
    check_keys(est, SETTINGS, "estimator")
    given = {}
    for key, value in est.items():
        s, where = SETTINGS[key], f"estimator.{key}"
        if s.optional and value in ("none", -1):
            given[key] = None
        elif s.table:
            given[key] = _sub_table(s.type, value, where)
        else:
            given[key] = scalar(value, where, s.type, low=s.low, choices=s.choices)
    try:
        return Params(**given)
    except ValueError as e:
        raise InputError("estimator", str(e)) from None


def _sub_table(kind, value, where: str):
    """A dataclass of settings (``[estimator.robust]``) from its table: each
    field read as the kind of its default (a default of None: a number;
    ``kind.CHOICES`` lists a string field's values), then the dataclass's
    own checks, an error naming the field."""
    defaults = {f.name: f.default for f in fields(kind)}
    if not isinstance(value, dict):
        raise InputError(where, "must be a table of settings")
    check_keys(value, defaults, where)
    choices = getattr(kind, "CHOICES", {})
    read = {}
    for k, v in value.items():
        t = float if defaults[k] is None else type(defaults[k])
        read[k] = scalar(v, f"{where}.{k}", t, choices=choices.get(k))
    try:
        return kind(**read)
    except ValueError as e:
        field, _, msg = str(e).partition(": ")
        raise InputError(f"estimator.{field}", msg) from None


def _parse_agent(a, i: int, n: int) -> AgentSpec:
    where = f"agents[{i}]"
    check_keys(a, AGENT_KEYS, where)
    H = matrix(a.get("H"), f"{where}.H")
    if H.shape[0] == 0 or H.shape[1] != n:
        raise InputError(f"{where}.H", f"must have at least one row and {n} columns (the state dimension), "
                                       f"got {H.shape[0]}x{H.shape[1]}")
    R = spd(matrix(a.get("R"), f"{where}.R", (H.shape[0], H.shape[0])), f"{where}.R")
    sense = setting(a, "sense", where, str, "quadrant", choices=SENSE_KINDS)
    path = a.get("path")
    if path is not None and "position" in a:
        raise InputError(f"{where}.position", "give either position (static) or path (mobile), not both")
    if path is None and ("period" in a or "phase" in a):
        raise InputError(f"{where}.{'period' if 'period' in a else 'phase'}", "applies only to a mobile agent (path)")
    return AgentSpec(
        id=i + 1, label=agent_id(a.get("id", i + 1), f"{where}.id"), H=H, R=R, sense=sense,
        sense_range=setting(a, "sense_range", where, float, np.inf, low=0.0, allow_inf=True),
        position=None if path is not None else vector(a.get("position", [0.0, 0.0]), f"{where}.position", 2),
        path=None if path is None else matrix(path, f"{where}.path", (None, 2)),
        period=setting(a, "period", where, float, 1.0, above=0.0),
        phase=setting(a, "phase", where, float, 0.0),
    )


MEMORY_BOUND = 2 * 2**30  # bytes a simulation (and its estimates) may ask for; above it is refused
TICK_BYTES_MAX = 1 << 28  # working set one tick of an engine batch may take (256 MiB)
# working set of one block of receivers a gathered tick fuses at once (32 MiB): larger blocks' arrays are past
# what the allocator keeps for reuse (glibc's mmap threshold, 32 MiB at most) and are faulted in afresh at every
# call (a tick of 10,000 random-geometric agents spent 45 % of its CPU in the kernel with 256 MiB blocks)
BLOCK_BYTES_MAX = 1 << 25
TICK_BYTES_PER_SLOT = 12 * 8  # ~12 live float arrays of (receiver, sender slot, n, n)
TICK_BYTES_PER_WEIGHT = 4 * 8  # and ~4 of (receiver, sender slot, model) where messages carry model weights
GATHER_BYTES_PER_SLOT = 32  # the gathered layout's sender index, place, weight and flags per (receiver, sender slot)


def gathers(N: int, D: int) -> bool:
    """Whether the engine hands N receivers their senders gathered (a padded
    list of D, the largest neighbourhood, per receiver) rather than dense
    (all N agents as senders of every receiver): a large (N >= 32) and
    sparse (no neighbourhood over half the agents) network."""
    return N >= 32 and 2 * D <= N


def simulation_bytes(N: int, K: int, n: int, p: int, m: int, seeds: int = 1, moving_links: bool = False,
                     degree: int | None = None) -> int:
    """About how many bytes ``simulate`` and an engine run of its trace hold:
    per seed, agent and tick the noise, measurements and estimates (x, P, d,
    S); the links, (N, N) bools once for static agents or per tick for
    moving ones; and the engine's layout of them with ``degree`` D the
    largest neighbourhood (N, the worst case, when not known): gathered
    (``gathers``), ``GATHER_BYTES_PER_SLOT`` per receiver and sender slot and
    a tick's working set, which receivers fused in blocks keep under
    ``BLOCK_BYTES_MAX``; dense, an (N, N) float adjacency and the working set
    of every pair (``TICK_BYTES_PER_SLOT`` n^2 each). Measured: an engine run
    of 10,000 random-geometric agents (D = 970) for 20 ticks peaks at 592
    MiB of resident memory, where this says 690 MiB."""
    per_agent_tick = 8 * (3 * p + 3 * n + 2 * n * n + 2 * m + 2 * m * m) + 2
    D = N if degree is None else min(int(degree), N)
    links = N * N * (K if moving_links else 1)
    if gathers(N, D):
        links += GATHER_BYTES_PER_SLOT * N * D + min(TICK_BYTES_PER_SLOT * n * n * N * D, BLOCK_BYTES_MAX)
    else:
        links += 8 * N * N + TICK_BYTES_PER_SLOT * n * n * N * N
    return seeds * K * N * per_agent_tick + K * N * 16 + links


def check_size(N: int, K: int, n: int, p: int, m: int, seeds: int = 1, moving_links: bool = False,
               degree: int | None = None) -> None:
    """``InputError`` when ``simulation_bytes`` is over ``MEMORY_BOUND``."""
    need = simulation_bytes(N, K, n, p, m, seeds, moving_links, degree)
    if need > MEMORY_BOUND:
        raise InputError("size", f"{N} agents x {K} ticks x {seeds} seeds need about {need / 2**30:.1f} GiB, "
                                 f"over the bound of {MEMORY_BOUND / 2**30:g} GiB; use fewer agents, ticks or seeds")


def _generate_agents(gen, n: int, agents: int | None, steps: int) -> tuple:
    check_keys(gen, GENERATE_KEYS, "generate")
    setting(gen, "kind", "generate", str, choices=("random-geometric",))
    if n < 2:
        raise InputError("generate", "generated agents see x, y or both: the state needs at least 2 dimensions")
    N = scalar(agents, "agents", int, low=1) if agents is not None else setting(gen, "agents", "generate", int, 100,
                                                                               low=1)
    links = N * N  # the (N, N) bool links, before drawing N positions: the ticks a command runs come later
    if links > MEMORY_BOUND:
        raise InputError("size", f"{N} agents need about {links / 2**30:.1f} GiB for their links alone, over the "
                                 f"bound of {MEMORY_BOUND / 2**30:g} GiB; use fewer agents")
    box = setting(gen, "box", "generate", float, 300.0, above=0.0)
    r = setting(gen, "R", "generate", float, 2.0, above=0.0)
    sense_range = setting(gen, "sense_range", "generate", float, 150.0, low=0.0, allow_inf=True)
    rng = np.random.default_rng(setting(gen, "layout_seed", "generate", int, 0, low=0))
    pos = rng.uniform(-box, box, size=(N, 2))
    kinds = [np.eye(n)[[0]], np.eye(n)[[1]], np.eye(n)[:2]]  # sees x, sees y, sees both
    out = []
    for i in range(N):
        H = kinds[i % 3]
        out.append(AgentSpec(id=i + 1, H=H, R=r * np.eye(H.shape[0]), sense="range",
                             sense_range=sense_range, position=pos[i]))
    return tuple(out)


# --------------------------------------------------------------------------
# simulation
# --------------------------------------------------------------------------
def static_links(kind: str, N: int) -> np.ndarray:
    """(N, N) bool adjacency of a fixed topology, diagonal True."""
    eye = np.eye(N, dtype=bool)
    if kind == "all":
        return np.ones((N, N), dtype=bool)
    if kind == "none":
        return eye
    if kind == "ring":
        i = np.arange(N)
        L = eye.copy()
        L[i, (i + 1) % N] = True
        L[i, (i - 1) % N] = True
        return L
    raise InputError("topology", f"no static adjacency for {kind!r}")


PAIRS_PER_BLOCK = 1 << 20  # agent pairs whose differences ``range_links`` forms at once


def range_links(positions: np.ndarray, comm_range: float) -> np.ndarray:
    """(..., N, N) bool: agents within ``comm_range`` of each other (inclusive),
    diagonal True. Symmetric by construction. Formed a block of receivers at
    a time: the differences of ``PAIRS_PER_BLOCK`` pairs at most (10,000
    agents would otherwise take 1.6 GB of differences for a 100 MB answer),
    each pair's squared distance the same arithmetic whatever the block."""
    N = positions.shape[-2]
    out = np.empty(positions.shape[:-2] + (N, N), dtype=bool)
    rows = max(1, PAIRS_PER_BLOCK // max(N, 1))
    for start in range(0, N, rows):
        diff = positions[..., start:start + rows, None, :] - positions[..., None, :, :]
        np.less_equal(np.einsum("...k,...k->...", diff, diff), comm_range * comm_range,
                      out=out[..., start:start + rows, :])
    return out


def sensing(scn: Scenario, target: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(B, K, N) bool: which agent measures the target at which tick.

    target: (B, K, 2) target position; positions: (K, N, 2)."""
    t = target[:, :, None, :]
    p = positions[None]
    out = np.zeros(t.shape[:2] + (scn.N,), dtype=bool)
    for i, a in enumerate(scn.agents):
        if a.sense == "always":
            out[:, :, i] = True
        elif a.sense == "quadrant":
            out[:, :, i] = np.all(np.sign(t[:, :, 0]) == np.sign(p[:, :, i]), axis=-1)
        else:
            out[:, :, i] = np.linalg.norm(t[:, :, 0] - p[:, :, i], axis=-1) <= a.sense_range
    return out


def links_for(scn: Scenario, positions: np.ndarray) -> np.ndarray:
    """(K, N, N) bool links at every tick.

    Range links are formed one tick at a time (never a (K, N, N, 2) array of
    differences), and once only when no agent moves: a read-only broadcast
    then stands for all K ticks, so 1,000 static agents cost one N x N."""
    K = positions.shape[0]
    if scn.topology == "range":
        if not any(a.mobile for a in scn.agents):
            return np.broadcast_to(range_links(positions[0], scn.comm_range), (K, scn.N, scn.N))
        return np.stack([range_links(p, scn.comm_range) for p in positions])
    return np.broadcast_to(static_links(scn.topology, scn.N), (K, scn.N, scn.N))


def simulate(scn: Scenario, seeds, steps: int | None = None) -> Trace:
    """Ground truth, measurements and links for every seed: a ``Trace`` with
    a leading seed axis. Seed s draws its process and measurement noise from
    ``numpy.random.default_rng(s)``, and each seed's products are its own
    (BLAS rounds a stack of rows otherwise than one row), so a seed's trace
    is the same bits whichever seeds are simulated beside it."""
    K = int(steps or scn.steps)
    scn.check_size(len(seeds) if isinstance(seeds, (list, tuple, range)) else int(np.size(seeds)), K)
    seeds = tuple(int(s) for s in np.atleast_1d(seeds))
    model = scn.model(K)
    sensors = scn.sensors()
    n, m, N, pmax = model.n, model.m, sensors.N, sensors.H.shape[1]
    B = len(seeds)
    Lq = np.linalg.cholesky(model.Q)
    Lr = np.linalg.cholesky(sensors.R)  # (N, p, p)
    W = np.empty((B, K, n))
    V = np.empty((B, K, N, pmax))
    for b, s in enumerate(seeds):
        rng = np.random.default_rng(s)
        W[b] = rng.standard_normal((K, n)) @ Lq.T
        V[b] = np.einsum("iab,kib->kia", Lr, rng.standard_normal((K, N, pmax)))
    d = np.stack([scn.inputs(K, s) for s in seeds])  # (B, K, m)
    x = np.empty((B, K, n))
    y = np.empty((B, K, N, pmax))
    A = [model.A_at(k) for k in range(1, K + 1)]
    for b in range(B):
        prev = model.x0[None]
        for k in range(K):
            prev = prev @ A[k].T + d[b:b + 1, k] @ model.G.T + W[b:b + 1, k]
            x[b, k] = prev[0]
        y[b] = np.einsum("ipn,bkn->bkip", sensors.H, x[b:b + 1])[0] + V[b]
    positions = scn.positions(K)
    has = sensing(scn, x[..., list(scn.position_dims)], positions)
    valid_rows = np.arange(pmax)[None, :] < sensors.p[:, None]  # (N, p)
    y = np.where(valid_rows & has[..., None], y, 0.0)
    links = links_for(scn, positions)[None]
    return Trace(
        model=model, sensors=sensors, y=y, has=has, links=links,
        truth_x=x, truth_d=d,
        positions=positions, seeds=seeds, position_dims=scn.position_dims, labels=scn.labels,
    )
