"""The estimators, by command-line name: DISKF, its robust variant and the five baselines."""
from __future__ import annotations

from .base import Algorithm, State
from .consensus_baselines import GDKF, KCF, DiffKF, gossip_draws
from .diskf import DISKF
from .diskf_robust import DISKFRobust
from .rkf_baselines import CDRKF, LDRKF

REGISTRY = {cls.name: cls for cls in (DISKF, DISKFRobust, CDRKF, LDRKF, KCF, DiffKF, GDKF)}
NAMES = tuple(REGISTRY)


def get(name: str):
    """Algorithm class by name; ValueError naming the choices otherwise."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}; choose from {', '.join(NAMES)}") from None


def parse_list(spec: str) -> list[str]:
    """'all' or a comma-separated list of names, validated."""
    names = list(NAMES) if spec.strip() == "all" else [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        raise ValueError("algorithms: empty list")
    for n in names:
        get(n)
    return names


__all__ = ["Algorithm", "State", "REGISTRY", "NAMES", "get", "parse_list", "gossip_draws"]
