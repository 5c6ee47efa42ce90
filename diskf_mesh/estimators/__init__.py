"""estimators: DISKF, its robust variant, the five baselines and any
installed plugin, by name.

Each estimator is a class (``base.Estimator``) that declares itself (name,
label, colour, parameters, hooks) and implements a local step (before
sending) and a fuse step (after receiving) over a batch of agents; the
engine and the agent process call the same two functions.

The registry: the built-ins below, then every entry point of the group
``diskf_mesh.estimators`` (value: the estimator class, e.g.
``example-local = "diskf_mesh_example_local:ExampleLocal"``), loaded once
when this package is imported, through the same ``register`` the built-ins
go through. ``Params`` is made from what they declare: one field per
``Setting`` of a registered estimator (docs/estimators.md).

May import: core.
"""
from __future__ import annotations

import warnings
from dataclasses import field, make_dataclass, replace
from importlib.metadata import entry_points

from diskf_mesh.estimators.base import EXCHANGED, Estimator, Exchanged, Setting, State, check_exchanged
from diskf_mesh.estimators.consensus_baselines import GDKF, KCF, DiffKF
from diskf_mesh.estimators.diskf import DISKF
from diskf_mesh.estimators.diskf_auto import DISKFAuto
from diskf_mesh.estimators.diskf_robust import DISKFNone, DISKFRobust
from diskf_mesh.estimators.rkf_baselines import CDRKF, LDRKF

ENTRY_POINTS = "diskf_mesh.estimators"
BUILTINS = (DISKF, DISKFRobust, DISKFAuto, DISKFNone, CDRKF, LDRKF, KCF, DiffKF, GDKF)


def register(cls, registry: dict, settings: dict) -> None:
    """Add an estimator class to ``registry`` {name: class} and its
    settings to ``settings`` {name: Setting}; ValueError if the class is not
    an ``Estimator`` with a fresh name and label, or declares a setting
    another estimator declares differently."""
    if not (isinstance(cls, type) and issubclass(cls, Estimator)):
        raise ValueError(f"{cls!r} is not a subclass of diskf_mesh.estimators.Estimator")
    if not cls.name or not isinstance(cls.name, str) or not cls.label:
        raise ValueError(f"{cls.__qualname__}: an estimator declares a name and a label")
    if cls.name in registry:
        raise ValueError(f"{cls.__qualname__}: the name {cls.name!r} is taken by {registry[cls.name].__qualname__}")
    for s in cls.settings:
        if not isinstance(s, Setting):
            raise ValueError(f"{cls.name}: settings must be Setting objects, got {s!r}")
        if s.name in settings and settings[s.name] != s:
            raise ValueError(f"{cls.name}: setting {s.name!r} is declared differently by another estimator")
        s.check(s.default)
    check_exchanged(cls)
    registry[cls.name] = cls
    settings.update({s.name: s for s in cls.settings})


def _load() -> tuple[dict, dict]:
    registry, settings = {}, {}
    for cls in BUILTINS:
        register(cls, registry, settings)
    for ep in sorted(entry_points(group=ENTRY_POINTS), key=lambda e: e.name):
        try:
            cls = ep.load()
            if getattr(cls, "name", None) != ep.name:
                raise ValueError(f"the entry point is named {ep.name!r}, the estimator {getattr(cls, 'name', None)!r}")
            register(cls, registry, settings)
        except Exception as e:  # a broken plugin must not take the built-ins down
            warnings.warn(f"estimator plugin {ep.name!r} ({ep.value}) not loaded: {e}", RuntimeWarning, stacklevel=2)
    return registry, settings


REGISTRY, SETTINGS = _load()
NAMES = tuple(REGISTRY)
# the estimator a run uses unless told otherwise: the automatic input model,
# within 10 % of each case's best in 90 % of the held-out suite's cases
# (docs/heldout.md); DISKF stays the paper's Algorithm 1, for comparison
DEFAULT = DISKFAuto.name
# 'all': every registered estimator, the default first (tables lead with it)
ALL = (DEFAULT, *(n for n in NAMES if n != DEFAULT))


def _check(self) -> None:
    for s in SETTINGS.values():
        s.check(getattr(self, s.name))


def _with_setting(self, name: str, **fields):
    """These parameters with fields of the setting ``name`` (a table, such
    as ``auto``) changed: ``params.with_setting("auto", noise_level=10.0)``."""
    return replace(self, **{name: replace(getattr(self, name), **fields)})


Params = make_dataclass(
    "Params", [(s.name, s.type | None if s.optional else s.type, field(default=s.default)) for s in SETTINGS.values()],
    frozen=True, namespace={"__post_init__": _check, "with_setting": _with_setting, "__module__": __name__})
Params.__doc__ = "The estimators' parameters (a scenario's [estimator] table), one field per Setting:\n\n" + "\n".join(
    f"    {s.name}: {s.doc} (default {s.default!r}; {', '.join(c.name for c in REGISTRY.values() if s in c.settings)})"
    for s in SETTINGS.values())


def get(name: str) -> type[Estimator]:
    """Estimator class by name; ValueError naming the choices otherwise."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; choose from {', '.join(NAMES)}") from None


def parse_list(spec: str) -> list[str]:
    """'all' or a comma-separated list of names, validated."""
    names = list(ALL) if spec.strip() == "all" else [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        raise ValueError("estimators: empty list")
    for n in names:
        get(n)
    return names


def label(name: str) -> str:
    """An estimator's label; the name itself for a series that is not one
    (e.g. the centralized bound, which labels itself)."""
    return REGISTRY[name].label if name in REGISTRY else name


def color(name: str) -> str | None:
    """An estimator's plot colour, or None."""
    return REGISTRY[name].color if name in REGISTRY else None


__all__ = ["Estimator", "Setting", "State", "Exchanged", "EXCHANGED", "Params", "REGISTRY", "SETTINGS", "NAMES", "ENTRY_POINTS",
           "get", "parse_list", "label", "color", "register"]
