"""docker-compose.yml: the world and every agent of Scenario 2, one service
each, running exactly the command lines the launcher builds (there is no
Docker engine here, so the file is checked, not run)."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

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
    assert set(services) == set(want)
    for name, argv in want.items():
        assert services[name]["command"] == [compose.PYTHON, *argv[1:]], name


def test_explicit_endpoints_and_one_image():
    services = _services()
    images = {s["image"] for s in services.values()}
    assert images == {"diskf-mesh"}
    world = services["world"]["command"]
    assert world[world.index("--listen") + 1] == f"tcp/0.0.0.0:{compose.PORT}"
    for name, s in services.items():
        cmd = s["command"]
        assert "--no-multicast-scouting" in cmd
        assert cmd[cmd.index("--run-id") + 1] == "compose"
        if name != "world":
            assert cmd[cmd.index("--connect") + 1] == f"tcp/world:{compose.PORT}"
            assert s["depends_on"] == ["world"]


def test_compose_file_is_up_to_date():
    assert (ROOT / "docker-compose.yml").read_text() == compose.render(), \
        "regenerate with: python -m sim.compose > docker-compose.yml"


def test_dockerfile_installs_the_package():
    text = (ROOT / "Dockerfile").read_text()
    assert "pip install" in text and text.startswith("#")
