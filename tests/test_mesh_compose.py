"""docker-compose.yml: the world and every agent of Scenario 2, one service
each, running exactly the command lines the launcher builds, authenticated by
the credentials a one-shot service writes (the files as text and the
credentials command; tests/test_compose_run.py runs them in an engine)."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from diskf_mesh.cli import main as cli
from diskf_mesh.mesh.security import credentials
from sim import compose
from sim.launcher import build_children

pytestmark = pytest.mark.mesh

ROOT = Path(__file__).resolve().parents[1]


def _services() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]


def test_every_service_runs_the_launchers_command_line(tmp_path):
    ids = [a.id for a in compose.SPEC.load().agents]
    assert len(ids) == 9
    world, agents = build_children(compose.SPEC, compose.TICKS, compose.SEED, ids, tmp_path, compose.WORLD_ZENOH,
                                   compose.AGENT_ZENOH, compose.WORLD_EXTRA)
    want = {"world": world.argv, **{f"agent-{i}": a.argv for i, a in zip(ids, agents)}}
    services = _services()
    assert set(services) == set(want) | {"credentials"}
    for name, argv in want.items():
        assert services[name]["command"] == [compose.PYTHON, *argv[1:]], name


def test_explicit_tls_endpoints_credentials_and_one_image():
    services = _services()
    images = {s["image"] for s in services.values()}
    assert images == {"diskf-mesh"}
    world = services["world"]["command"]
    assert world[world.index("--listen") + 1] == f"tls/0.0.0.0:{compose.PORT}"
    assert services["world"]["depends_on"] == {"credentials": {"condition": "service_completed_successfully"}}
    assert f"{compose.RESULTS}:/results" in services["world"]["volumes"]
    for name, s in services.items():
        assert s["init"] is True, name  # SIGTERM reaches the process: no stop waits for the kill
        cmd = s["command"]
        assert cmd[cmd.index("--run-id") + 1] == "compose"
        assert s["user"] == "${DISKF_UID:-10001}:${DISKF_GID:-10001}"  # not root; the host user's ids if given
        if name == "credentials":
            assert s["volumes"] == ["credentials:/credentials"]
            continue
        assert "--no-multicast-scouting" in cmd and "--insecure" not in cmd
        assert cmd[cmd.index("--credentials") + 1] == compose.CREDENTIALS
        assert "credentials:/credentials:ro" in s["volumes"]
        assert s["healthcheck"]["test"][0] == "CMD"
        if name != "world":
            assert cmd[cmd.index("--connect") + 1] == f"tls/world:{compose.PORT}"
            assert s["depends_on"] == {"world": {"condition": "service_healthy"}}
    assert "credentials" in yaml.safe_load((ROOT / "docker-compose.yml").read_text())["volumes"]


def test_the_credentials_service_writes_what_every_service_reads(tmp_path, capsys):
    """The credentials service's command, run here with the volume's path
    moved to a temporary directory: every mesh service's identity is in it."""
    argv = _services()["credentials"]["command"]
    assert argv[0] == "diskf-mesh"
    out = tmp_path / "compose"
    argv = [str(out) if a == compose.CREDENTIALS else a for a in argv[1:]]
    assert cli.main(argv) == 0 and cli.main(argv) == 0  # --replace: a fresh CA on every compose up
    capsys.readouterr()
    for name, s in _services().items():
        if name != "credentials":
            who = credentials.WORLD if name == "world" else credentials.agent_identity(int(name.split("-")[1]))
            assert credentials.load(out, who, "compose").name == who


def test_compose_file_is_up_to_date():
    assert (ROOT / "docker-compose.yml").read_text() == compose.render(), \
        "regenerate with: python -m sim.compose > docker-compose.yml"


def test_dockerfile_installs_the_package_and_runs_as_a_user():
    text = (ROOT / "Dockerfile").read_text()
    assert "pip install" in text and text.startswith("#")
    base = next(ln.split()[1] for ln in text.splitlines() if ln.startswith("FROM "))
    assert ":" in base and base.split(":")[1][0].isdigit()  # a pinned release, not a floating tag
    user = [ln.split()[1] for ln in text.splitlines() if ln.startswith("USER ")]
    assert user and user[-1] not in ("root", "0")


def test_the_image_lock_pins_every_runtime_dependency_within_its_bounds():
    """The Dockerfile installs requirements.lock: every dependency of
    pyproject.toml is pinned there (==) to a version its bounds allow, and
    the image has no plotting stack."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    root = Path(__file__).resolve().parents[1]
    deps = [Requirement(d) for d in tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]]
    pins = {}
    for line in (root / "requirements.lock").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[canonicalize_name(name)] = version.strip()
    for d in deps:
        assert canonicalize_name(d.name) in pins, f"{d.name} is not pinned in requirements.lock"
        assert d.specifier.contains(pins[canonicalize_name(d.name)]), f"{d.name}=={pins[canonicalize_name(d.name)]}"
    assert "matplotlib" not in pins
    assert "requirements.lock" in (root / "Dockerfile").read_text()


# --------------------------------------------------------------------------
# docker-compose.hosts.yml: two "hosts" (router + shard each) and the world
# --------------------------------------------------------------------------
def _hosts_services() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.hosts.yml").read_text())["services"]


def test_the_hosts_file_runs_the_command_lines_of_up_hosts(tmp_path):
    """Every service of the two-host file runs what ``up --hosts`` would start
    for the same plan (``sim.hosts.children``): the world as a router, a
    router per host connected to the world and the routers before it, a
    shard per host whose agents are clients of its router."""
    from sim import hosts

    plan = hosts.parse({"credentials": compose.HOSTS_CREDENTIALS,
                        "world": {"listen": f"tls/world:{compose.PORT}", "bind": f"tls/0.0.0.0:{compose.PORT}",
                                  "python": compose.PYTHON},
                        "hosts": {name: {"agents": ids, "router": f"tls/router-{name}:{compose.PORT}",
                                         "router_bind": f"tls/0.0.0.0:{compose.PORT}", "python": compose.PYTHON}
                                  for name, ids in (("a", "1-5"), ("b", "6-9"))}})
    plan.check([a.id for a in compose.HOSTS_SPEC.load().agents])
    world, routers, shards = hosts.children(plan, compose.HOSTS_SPEC, compose.TICKS, compose.SEED,
                                            compose.ZenohOptions(credentials=plan.credentials), tmp_path,
                                            compose.HOSTS_WORLD_EXTRA)
    want = {"world": world.argv, "router-a": routers[0].argv, "router-b": routers[1].argv,
            "host-a": shards[0].argv, "host-b": shards[1].argv}
    services = _hosts_services()
    assert set(services) == set(want) | {"credentials"}
    for name, argv in want.items():
        assert services[name]["command"] == argv, name
    w = services["world"]["command"]
    assert w[w.index("--mode") + 1] == "router"
    rb = services["router-b"]["command"]
    assert [rb[i + 1] for i, a in enumerate(rb) if a == "--connect"] == [f"tls/world:{compose.PORT}",
                                                                       f"tls/router-a:{compose.PORT}"]
    for name in ("host-a", "host-b"):
        cmd = services[name]["command"]
        assert cmd[cmd.index("--mode") + 1] == "client"
        assert cmd[cmd.index("--connect") + 1] == f"tls/router-{name[-1]}:{compose.PORT}"
        assert services[name]["depends_on"] == {f"router-{name[-1]}": {"condition": "service_healthy"}}
    assert services["router-b"]["depends_on"] == {"world": {"condition": "service_healthy"},
                                                  "router-a": {"condition": "service_healthy"}}
    for name, s in services.items():
        cmd = s["command"]
        assert "--insecure" not in cmd and s["init"] is True
        if name != "credentials":
            assert cmd[cmd.index("--credentials") + 1] == compose.HOSTS_CREDENTIALS
            assert "credentials:/credentials:ro" in s["volumes"]


def test_the_hosts_credentials_service_makes_the_routers_identity(tmp_path, capsys):
    argv = _hosts_services()["credentials"]["command"]
    out = tmp_path / "c"
    assert cli.main([str(out) if a == compose.HOSTS_CREDENTIALS else a for a in argv[1:]]) == 0
    capsys.readouterr()
    assert credentials.load(out, credentials.ROUTER, compose.HOSTS_SPEC.run_id).router


def test_the_hosts_compose_file_is_up_to_date():
    assert (ROOT / "docker-compose.hosts.yml").read_text() == compose.render_hosts(), \
        "regenerate with: python -m sim.compose --hosts > docker-compose.hosts.yml"
