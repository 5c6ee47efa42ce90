"""The unknown input d_k of a scenario (its ``[input]`` table), by kind.

d_k acts between tick k and k+1 (k = 0..K-1), in the input's own units (the
state moves by G d_k). Kinds (docs/formats.md, ``[input]``):

    step       ``before`` for k < ``at``, ``after`` (or ``value``) from then on
    constant   ``value`` (or ``after``) at every tick
    sine       ``offset`` + ``amplitude`` sin(2 pi (k - ``at``) / ``period`` + ``phase``) from ``at`` on
    ramp       ``before`` + ``slope`` (k - ``at``) from ``at`` on, ``before`` until then
    steps      random steps at random intervals: from ``at`` on, each tick
               starts a new level with probability 1 / ``interval``; a level
               is ``offset`` + ``scale`` * N(0, I) (0 before the first one)
    telegraph  from ``at`` on, ``offset`` +- ``amplitude``, the sign flipping
               every ``interval`` ticks (``random = false``) or with
               probability 1 / ``interval`` per tick (``random = true``, the
               default); it starts at +
    white      ``offset`` + ``scale`` * N(0, I) drawn independently every tick
    series     ``values``: one row of m numbers per tick (or one number per
               tick when m = 1), or ``file``: a text file of the same rows
               (whitespace or commas, ``#`` comments); past its last row the
               last value holds

The seed rule of the random kinds (steps, telegraph, white): with
``seed`` given, the input is drawn from ``numpy.random.default_rng(seed)``
and is the same for every simulation seed; without it, simulation seed s
draws it from ``numpy.random.default_rng([s, 1])``, a stream independent of
the noise (``default_rng(s)``), so a seed's noise is the same whatever the
input kind. The other kinds draw nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diskf_mesh.core.errors import InputError
from diskf_mesh.data.validate import check_keys, matrix, scalar, setting, vector

KINDS = ("step", "constant", "sine", "ramp", "steps", "telegraph", "white", "series")
RANDOM_KINDS = ("steps", "telegraph", "white")
# the keys each kind reads ("kind" and "seed" aside)
KIND_KEYS = {
    "step": ("at", "before", "after", "value"),
    "constant": ("value", "after"),
    "sine": ("at", "amplitude", "period", "phase", "offset"),
    "ramp": ("at", "before", "slope"),
    "steps": ("at", "scale", "interval", "offset"),
    "telegraph": ("at", "amplitude", "interval", "random", "offset"),
    "white": ("at", "scale", "offset"),
    "series": ("values", "file"),
}
INPUT_KEYS = ("kind", "seed") + tuple(sorted({k for keys in KIND_KEYS.values() for k in keys}))
STREAM = 1  # the second entropy word of the random kinds' stream


@dataclass(frozen=True)
class InputSpec:
    """A scenario's ``[input]``, validated; ``values`` (m-long vectors) are
    set for the keys its kind reads, zeros elsewhere."""

    kind: str = "step"
    at: int = 0
    before: np.ndarray | None = None
    after: np.ndarray | None = None
    amplitude: np.ndarray | None = None
    offset: np.ndarray | None = None
    slope: np.ndarray | None = None
    scale: np.ndarray | None = None
    period: float = 20.0
    phase: float = 0.0
    interval: float = 10.0
    random: bool = True
    series: np.ndarray | None = None   # (rows, m)
    seed: int | None = None

    def stream(self, sim_seed: int) -> np.random.Generator:
        """The random kinds' generator for simulation seed ``sim_seed`` (the seed rule above)."""
        if self.seed is not None:
            return np.random.default_rng(self.seed)
        return np.random.default_rng([int(sim_seed), STREAM])

    def values(self, steps: int, sim_seed: int = 0) -> np.ndarray:
        """(steps, m): d_k for k = 0..steps-1 under simulation seed ``sim_seed``."""
        k = np.arange(steps, dtype=float)[:, None]
        on = k >= self.at
        t = k - self.at
        kind = self.kind
        if kind == "step":
            return np.where(on, self.after, self.before)
        if kind == "constant":
            return np.broadcast_to(self.after, (steps, len(self.after))).copy()
        if kind == "sine":
            return np.where(on, self.offset + self.amplitude * np.sin(2 * np.pi * t / self.period + self.phase), 0.0)
        if kind == "ramp":
            return self.before + self.slope * np.maximum(t, 0.0)
        if kind == "series":
            rows = np.minimum(np.arange(steps), len(self.series) - 1)
            return self.series[rows].copy()
        rng = self.stream(sim_seed)
        m = len(self.offset)
        if kind == "white":
            draws = rng.standard_normal((steps, m))
            return np.where(on, self.offset + self.scale * draws, 0.0)
        if kind == "steps":
            starts = rng.random(steps) < 1.0 / self.interval     # a new level starts at tick k
            levels = self.offset + self.scale * rng.standard_normal((steps, m))
            starts &= on[:, 0]
            idx = np.maximum.accumulate(np.where(starts, np.arange(steps), -1))  # the last start at or before k
            return np.where((idx >= 0)[:, None], levels[np.maximum(idx, 0)], 0.0)
        # telegraph
        if self.random:
            flips = rng.random(steps) < 1.0 / self.interval
        else:
            flips = (t[:, 0] > 0) & (np.mod(t[:, 0], self.interval) == 0)
        flips &= on[:, 0]
        sign = np.where(np.cumsum(flips) % 2 == 0, 1.0, -1.0)[:, None]
        return np.where(on, self.offset + sign * self.amplitude, 0.0)


def parse_input(inp, m: int, base: Path | None = None) -> InputSpec:
    """An ``InputSpec`` from a scenario's ``[input]`` table (m: the input
    dimension; ``base``: the folder a relative ``file`` is read from).
    Every key is checked; a key the kind does not read is an error."""
    check_keys(inp, INPUT_KEYS, "input")
    kind = setting(inp, "kind", "input", str, "step", choices=KINDS)
    for key in inp:
        if key not in ("kind", "seed") + KIND_KEYS[kind]:
            raise InputError(f"input.{key}", f"is not used with kind = {kind!r} (it reads: "
                                             f"{', '.join(KIND_KEYS[kind])})")
    zeros = np.zeros(m)

    def vec(key, default=zeros):
        v = inp.get(key)
        if v is None:
            return default
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v] * m  # one number stands for every component
        return vector(v, f"input.{key}", m)

    if kind == "series":
        rows = _series(inp, m, base)
        return InputSpec(kind=kind, series=rows, offset=zeros)
    if "seed" in inp and kind not in RANDOM_KINDS:
        raise InputError("input.seed", f"is not used with kind = {kind!r} (only {', '.join(RANDOM_KINDS)} draw)")
    after = vec("after", vec("value")) if kind in ("step", "constant") else zeros
    spec = InputSpec(
        kind=kind, at=setting(inp, "at", "input", int, 0, low=0), before=vec("before"), after=after,
        amplitude=vec("amplitude", np.ones(m)), offset=vec("offset"), slope=vec("slope", np.ones(m)),
        scale=vec("scale", np.ones(m)),
        period=setting(inp, "period", "input", float, 20.0, above=0.0),
        phase=setting(inp, "phase", "input", float, 0.0),
        interval=setting(inp, "interval", "input", float, 10.0, low=1.0),
        random=setting(inp, "random", "input", bool, True),
        seed=setting(inp, "seed", "input", int, None, low=0),
    )
    if kind in ("steps", "white") and (spec.scale < 0).any():
        raise InputError("input.scale", "must be non-negative")
    if kind == "telegraph" and not spec.random and spec.interval != int(spec.interval):
        raise InputError("input.interval", f"must be a whole number of ticks with random = false, got {spec.interval!r}")
    return spec


def _series(inp, m: int, base: Path | None) -> np.ndarray:
    if ("values" in inp) == ("file" in inp):
        raise InputError("input.values", "kind = 'series' needs exactly one of values or file")
    if "values" in inp:
        v, where = inp["values"], "input.values"
    else:
        name = scalar(inp["file"], "input.file", str)
        path = Path(name) if base is None or Path(name).is_absolute() else base / name
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as e:
            raise InputError("input.file", f"cannot read {path}: {e}") from None
        v, where = [], f"input.file ({path})"
        for n, line in enumerate(text.splitlines(), 1):
            line = line.split("#", 1)[0].replace(",", " ").split()
            if line:
                try:
                    v.append([float(x) for x in line])
                except ValueError:
                    raise InputError(where, f"line {n}: not numbers: {' '.join(line)[:40]!r}") from None
    if isinstance(v, list) and v and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        v = [[x] for x in v]  # one number per tick
    if isinstance(v, list) and not v:
        raise InputError(where, "must have at least one row")
    return matrix(v, where, (None, m))
