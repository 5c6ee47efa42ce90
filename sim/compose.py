"""``docker-compose.yml``: the world and Scenario 2's nine agents, one
container each, all from one image, authenticated as ``diskf-mesh up`` runs
are (docs/docker.md):

* a one-shot ``credentials`` service writes the run's credentials
  (``diskf-mesh credentials``: a fresh CA on every ``docker compose up``)
  to the ``credentials`` volume, which every other service mounts read-only
  and passes as ``--credentials``;
* they meet on explicit TLS endpoints (multicast does not cross Docker
  bridges): the world listens on ``tls/0.0.0.0:7447``, every agent connects
  to ``tls/world:7447`` and listens on its own ``tls/0.0.0.0:7447``, and
  the agents find each other through the world;
* the world starts once the credentials are written, the agents once the
  world's port answers (health checks); the results go to ``./results``
  (or ``$DISKF_RESULTS``), written as the user ``DISKF_UID:DISKF_GID`` (set
  them to your own ids to read them; default: the image's user, 10001);
* every service runs under an init (``init: true``), which forwards SIGTERM
  to the process at any moment, so that ``stop`` and ``down`` never wait
  for the kill (``diskf_mesh.mesh.process.stopping``).

``docker/demo.sh`` runs a file to its end with compose v1 or v2 (detached,
then waits for the world's exit: the one-shot ``credentials`` service must
not end the run, as it would under ``--abort-on-container-exit``).

Every mesh command line comes from ``runspec.world_command`` and
``runspec.agent_command``, the functions ``diskf-mesh up`` uses; regenerate
the file after changing them:

    python -m sim.compose > docker-compose.yml

``docker-compose.hosts.yml`` is the same run over two "hosts"
(docs/hosts.md): the world (a zenoh router), and per host a router
(``diskf-mesh router``) and a shard of agents (``diskf-mesh host``: agents
1-5 on host a, 6-9 on host b, zenoh clients of their router), from the
command lines ``up --hosts`` starts (``sim.hosts.children``):

    python -m sim.compose --hosts > docker-compose.hosts.yml
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from diskf_mesh.mesh.process.runspec import RunSpec, agent_command, world_command
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from sim import hosts

SPEC = RunSpec("dynamic", run_id="compose")
TICKS, SEED, PORT = 200, 0, 7447
PYTHON = "python"  # the image's interpreter
CREDENTIALS = "/credentials/compose"  # in the credentials volume
WORLD_ZENOH = ZenohOptions(listen=(f"tls/0.0.0.0:{PORT}",), no_multicast_scouting=True, credentials=CREDENTIALS)
AGENT_ZENOH = ZenohOptions(connect=(f"tls/world:{PORT}",), listen=(f"tls/0.0.0.0:{PORT}",),
                           no_multicast_scouting=True, credentials=CREDENTIALS)
# containers start one python each (no zygote), all at once: a loaded machine needs more than the 30 s default
STARTUP = ("--startup-timeout", "120")
WORLD_EXTRA = ("--json", "/results/compose.json", "--estimates", "/results/compose-estimates.json", *STARTUP)
USER = "${DISKF_UID:-10001}:${DISKF_GID:-10001}"
RESULTS = "${DISKF_RESULTS:-./results}"  # where the world's results land on the host
# a mesh process is up once its zenoh port accepts connections
HEALTH = [PYTHON, "-c", f"import socket; socket.create_connection(('127.0.0.1', {PORT}), 2).close()"]


def credentials_command(spec: RunSpec = SPEC, out: str = CREDENTIALS) -> list:
    return ["diskf-mesh", "credentials", "--run-id", spec.run_id, "--out", out, "--scenario", spec.scenario,
            "--replace"]


def services(spec: RunSpec = SPEC) -> dict:
    """{service name: command line} of the mesh processes, the world first."""
    out = {"world": world_command(spec, TICKS, SEED, WORLD_ZENOH, WORLD_EXTRA, python=PYTHON)}
    for a in spec.load().agents:
        out[f"agent-{a.id}"] = agent_command(spec, a.id, AGENT_ZENOH, python=PYTHON)
    return out


HOSTS_SPEC = RunSpec("dynamic", run_id="compose-hosts")
HOSTS_CREDENTIALS = "/credentials/compose-hosts"
HOSTS_PLAN = hosts.HostsPlan(
    f"tls/world:{PORT}", (hosts.Shard("a", tuple(range(1, 6)), f"tls/router-a:{PORT}", python=PYTHON,
                                      router_bind=f"tls/0.0.0.0:{PORT}"),
                          hosts.Shard("b", tuple(range(6, 10)), f"tls/router-b:{PORT}", python=PYTHON,
                                      router_bind=f"tls/0.0.0.0:{PORT}")),
    world_python=PYTHON, credentials=HOSTS_CREDENTIALS, world_bind=f"tls/0.0.0.0:{PORT}")
HOSTS_WORLD_EXTRA = ("--json", "/results/compose-hosts.json", "--estimates", "/results/compose-hosts-estimates.json",
                     *STARTUP)


def hosts_services(spec: RunSpec = HOSTS_SPEC) -> dict:
    """{service name: (command line, services it waits for)} of the two-host
    run, from ``sim.hosts.children``: world, then router and shard per host."""
    world, routers, shards = hosts.children(HOSTS_PLAN, spec, TICKS, SEED, ZenohOptions(credentials=HOSTS_CREDENTIALS),
                                            Path("."), HOSTS_WORLD_EXTRA)
    out = {"world": (world.argv, {"credentials": "service_completed_successfully"})}
    before = {}
    for s, router, shard in zip(HOSTS_PLAN.shards, routers, shards):
        out[f"router-{s.name}"] = (router.argv, {"world": "service_healthy", **before})
        out[f"host-{s.name}"] = (shard.argv, {f"router-{s.name}": "service_healthy"})
        before[f"router-{s.name}"] = "service_healthy"  # the next router connects to this one
    return out


def _render(spec: RunSpec, credentials: str, procs: dict, what: str) -> str:
    # init: an init as PID 1 forwards SIGTERM (the kernel ignores it for a PID 1 without a handler)
    common = ["    build: .", "    image: diskf-mesh", f'    user: "{USER}"', "    init: true"]
    lines = [
        f"# Generated by `python -m sim.compose{what}` from the command lines `diskf-mesh up` uses;",
        "# tests/test_mesh_compose.py checks that they match. One image, one service per process.",
        f"# Run: docker/demo.sh{' docker-compose.hosts.yml' if what else ''} (docs/docker.md"
        + (", docs/hosts.md)." if what else ")."),
        "services:",
        "  credentials:", *common, f"    command: {json.dumps(credentials_command(spec, credentials))}",
        "    volumes:", "      - credentials:/credentials",
    ]
    for name, (argv, after) in procs.items():
        lines += [f"  {name}:", *common, f"    command: {json.dumps(argv)}"]
        if not name.startswith("host-"):  # a shard listens on no port of its own
            lines += ["    healthcheck:", f"      test: {json.dumps(['CMD', *HEALTH])}",
                      "      interval: 2s", "      timeout: 3s", "      retries: 30"]
        lines += ["    volumes:", "      - credentials:/credentials:ro"]
        if name == "world":
            lines.append(f"      - {RESULTS}:/results")
        lines.append("    depends_on:")
        for dep, condition in after.items():
            lines += [f"      {dep}:", f"        condition: {condition}"]
    lines += ["volumes:", "  credentials: {}"]
    return "\n".join(lines) + "\n"


def render(spec: RunSpec = SPEC) -> str:
    procs = {name: (argv, {"credentials": "service_completed_successfully"} if name == "world"
                    else {"world": "service_healthy"}) for name, argv in services(spec).items()}
    return _render(spec, CREDENTIALS, procs, "")


def render_hosts(spec: RunSpec = HOSTS_SPEC) -> str:
    return _render(spec, HOSTS_CREDENTIALS, hosts_services(spec), " --hosts")


if __name__ == "__main__":
    print(render_hosts() if sys.argv[1:] == ["--hosts"] else render(), end="")
