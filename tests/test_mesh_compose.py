"""docker-compose.yml: the world and every agent of Scenario 2, one service
each, running exactly the command lines the launcher builds, authenticated by
the credentials a one-shot service writes (there is no Docker engine here, so
the file is checked, not run; the credentials command itself is run)."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from diskf_mesh.cli import main as cli
from diskf_mesh.mesh import credentials
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
    assert "./results:/results" in services["world"]["volumes"]
    for name, s in services.items():
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
