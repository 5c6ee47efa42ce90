"""``up --hosts FILE``: one run over several hosts, from a small TOML file.

    # hosts.toml
    credentials = "/shared/creds"          # optional: made by `diskf-mesh credentials`, at this
                                           # path on every host (default: fresh ones in memory,
                                           # each process handed its own on standard input,
                                           # which the prefix must pass on: ssh does)
    [world]
    listen = "tls/10.0.0.1:7447"           # the world's endpoint (it runs as a zenoh router)
    bind = "tls/0.0.0.0:7447"              # optional: where it listens, if not on that address
    prefix = ["ssh", "w1"]                 # how to run a command there (default: here)
    python = "/opt/diskf/bin/python"       # its interpreter (default: this one)

    [hosts.a]                              # one table per host, named
    agents = "1-25"                        # its agents' ids (ranges and commas: "1-20,31")
    router = "tls/10.0.0.2:7447"           # optional: a router there, listening here;
                                           # without one the agents connect to the world
    router_bind = "tls/0.0.0.0:7447"       # optional, as the world's bind
    prefix = ["ip", "netns", "exec", "a"]  # optional, as for the world (a string is split
    python = "python3"                     # like a shell would)

Every agent id of the scenario is on exactly one host. ``up`` starts the
world, then every host's router (``diskf-mesh router``, connecting to the
world and to the routers of the hosts named before it: zenoh's routers
find the shortest path between any two hosts), then every host's shard
(``diskf-mesh host``: one process per agent, zenoh clients of their host's
router). ``children`` builds those command lines; ``up`` and
``docker-compose.hosts.yml`` (``sim.compose``) use it. Bad input (an
unknown key, a bad range, an id on two hosts or on none) is an
``InputError``: one line, exit 2.
"""
from __future__ import annotations

import shlex
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process import runspec
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from sim.child import Child

TOP_KEYS = ("credentials", "world", "hosts")
WORLD_KEYS = ("listen", "bind", "prefix", "python")
HOST_KEYS = ("agents", "router", "router_bind", "prefix", "python")


@dataclass(frozen=True)
class Shard:
    name: str
    ids: tuple
    router: str | None = None  # the router's listen endpoint, if the host runs one
    prefix: tuple = ()
    python: str | None = None
    router_bind: str | None = None  # where the router listens, if not on ``router``


@dataclass(frozen=True)
class HostsPlan:
    world_listen: str
    shards: tuple
    world_prefix: tuple = ()
    world_python: str | None = None
    credentials: str | None = None
    world_bind: str | None = None  # where the world listens, if not on ``world_listen``

    @property
    def ids(self) -> tuple:
        return tuple(sorted(i for s in self.shards for i in s.ids))

    @property
    def routerless(self) -> tuple:
        """Names of the hosts without a router: their agents are clients of
        the world, which forwards their traffic (``credentials.make``'s
        ``world_routes``)."""
        return tuple(s.name for s in self.shards if s.router is None)

    def check(self, ids) -> None:
        """Every agent id of the scenario (``ids``) on exactly one host."""
        where = {}
        for s in self.shards:
            for i in s.ids:
                if i in where:
                    raise InputError("hosts", f"agent {i} is on two hosts ({where[i]} and {s.name})")
                where[i] = s.name
        stray = sorted(set(where) - set(ids))
        if stray:
            raise InputError("hosts", f"agent {', '.join(map(str, stray))} is not in the scenario "
                                      f"(ids {runspec.id_ranges(ids)})")
        missing = sorted(set(ids) - set(where))
        if missing:
            raise InputError("hosts", f"agent {runspec.id_ranges(missing)} is on no host")


def _keys(table, allowed, where: str) -> dict:
    if not isinstance(table, dict):
        raise InputError("hosts", f"{where} must be a table")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise InputError("hosts", f"unknown key {unknown[0]!r} in {where} (known: {', '.join(allowed)})")
    return table


def _text(table: dict, key: str, where: str, required: bool = False):
    v = table.get(key)
    if v is None and required:
        raise InputError("hosts", f"{where} needs {key!r}")
    if v is not None and (not isinstance(v, str) or not v.strip()):
        raise InputError("hosts", f"{where}.{key} must be a non-empty string")
    return v


def _prefix(table: dict, where: str) -> tuple:
    v = table.get("prefix", ())
    if isinstance(v, str):
        return tuple(shlex.split(v))
    if not isinstance(v, (list, tuple)) or not all(isinstance(a, str) for a in v):
        raise InputError("hosts", f"{where}.prefix must be a list of strings (or one string)")
    return tuple(v)


def parse(doc: dict) -> HostsPlan:
    _keys(doc, TOP_KEYS, "the hosts file")
    world = _keys(doc.get("world", {}), WORLD_KEYS, "[world]")
    hosts = _keys(doc.get("hosts", {}), (*doc.get("hosts", {}),), "[hosts]")
    if not hosts:
        raise InputError("hosts", "no [hosts.NAME] table")
    shards = []
    for name, table in hosts.items():
        where = f"[hosts.{name}]"
        _keys(table, HOST_KEYS, where)
        agents = table.get("agents")
        if agents is None:
            raise InputError("hosts", f"{where} needs 'agents' (e.g. \"1-25\")")
        try:
            ids = runspec.parse_ids(str(agents))
        except InputError as e:
            raise InputError("hosts", f"{where}.agents: {e.message}") from None
        router = _text(table, "router", where)
        if table.get("router_bind") is not None and router is None:
            raise InputError("hosts", f"{where}.router_bind needs {where}.router (the address to connect to)")
        shards.append(Shard(name, ids, router, _prefix(table, where), _text(table, "python", where),
                            _text(table, "router_bind", where)))
    return HostsPlan(_text(world, "listen", "[world]", required=True), tuple(shards), _prefix(world, "[world]"),
                     _text(world, "python", "[world]"), _text(doc, "credentials", "the hosts file"),
                     _text(world, "bind", "[world]"))


def load(path) -> HostsPlan:
    try:
        doc = tomllib.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise InputError("hosts", f"cannot read {path}: {getattr(e, 'strerror', None) or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError("hosts", f"{path} is not valid TOML: {e}") from None
    return parse(doc)


def children(plan: HostsPlan, spec: RunSpec, ticks: int, seed: int, base: ZenohOptions, logs: Path,
             world_extra=(), agent_extra=()) -> tuple:
    """(world, routers, shards) of the run as ``Child``\\ ren; ``base``
    carries the credentials (or ``--insecure``). The world is a zenoh
    router listening on its endpoint; a host's router connects to the world
    and to the routers before it; a shard's agents are clients of their
    host's router (or of the world)."""
    base = replace(base, no_multicast_scouting=True)
    wz = replace(base, mode="router", listen=(plan.world_bind or plan.world_listen,))
    world = Child("world", [*plan.world_prefix, *runspec.world_command(spec, ticks, seed, wz, world_extra,
                                                                       python=plan.world_python)],
                  logs / "world.log", identities=(credentials.WORLD,))
    routers, shards, earlier = [], [], []
    for s in plan.shards:
        if s.router:
            rz = replace(base, listen=(s.router_bind or s.router,), connect=(plan.world_listen, *earlier))
            routers.append(Child(f"router {s.name}", [*s.prefix, *runspec.router_command(spec.run_id, rz, s.python)],
                                 logs / f"router-{s.name}.log", identities=(credentials.ROUTER,)))
            earlier.append(s.router)
        hz = replace(base, mode="client", connect=(s.router or plan.world_listen,))
        shards.append(Child(f"host {s.name}", [*s.prefix, *runspec.host_command(spec, s.ids, hz, agent_extra,
                                                                                 s.python)],
                            logs / f"host-{s.name}.log",
                            identities=tuple(credentials.agent_identity(i) for i in s.ids)))
    return world, routers, shards
