"""estimators: DISKF, its robust variant and the five baselines, by name.

Each estimator is a local step (before sending) and a fuse step (after
receiving) over a batch of agents; the engine and the agent process call
the same two functions.

May import: core.
"""
from __future__ import annotations

from diskf_mesh.estimators.base import Algorithm, State
from diskf_mesh.estimators.consensus_baselines import GDKF, KCF, DiffKF, gossip_draws
from diskf_mesh.estimators.diskf import DISKF
from diskf_mesh.estimators.diskf_robust import DISKFRobust
from diskf_mesh.estimators.rkf_baselines import CDRKF, LDRKF

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
