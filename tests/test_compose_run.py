"""The compose demo run for real: a Docker engine (Debian's docker.io; CI
installs it, see .ci/run), the image built from the Dockerfile (on a stand-in
base image from Debian packages where the FROM image cannot be pulled:
docker/build-base-image.sh), both compose files run by docker/demo.sh as
docs/docker.md says, and every service stopped by SIGTERM mid-run.

The engine: the one running, or a dockerd started here with neither iptables
rules nor ip_forward (the builds use the host's network, the containers only
their own bridge), stopped at the end with every change it made undone.
Containers, networks and volumes are removed on every path; the images stay,
as the build cache of the next run (the one a build replaces is removed). Where no engine can be had the tests are
skipped with one line saying why. Select them with ``-m docker``.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from mesh_helpers import assert_engine_bit_for_bit
from sim import compose

pytestmark = [pytest.mark.docker, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
IMAGE = "diskf-mesh"
BUILD_TIMEOUT_S = 900  # a cold build: Debian packages for the base image, the lock's wheels
RUN_TIMEOUT_S = 240
STOP_WITHIN_S = 2.0
STOP_GRACE_S = 10  # what docker gives before SIGKILL: a stop that took it shows as exit 137
FILES = {"docker-compose.yml": compose.SPEC, "docker-compose.hosts.yml": compose.HOSTS_SPEC}


def _run(cmd, timeout, check=True, **kw) -> subprocess.CompletedProcess:
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)
    if check and done.returncode:
        raise AssertionError(f"{' '.join(map(str, cmd))} exited {done.returncode}: {done.stderr.strip()[-2000:]}")
    return done


def _docker_ok() -> bool:
    try:
        return _run(["docker", "info"], 20, check=False).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def _compose_cmd() -> list | None:
    if shutil.which("docker") and _run(["docker", "compose", "version"], 20, check=False).returncode == 0:
        return ["docker", "compose"]
    return ["docker-compose"] if shutil.which("docker-compose") else None


class HostState:
    """What a dockerd may change on the host, to undo: ip_forward, the nft
    tables, the docker0 bridge."""

    def __init__(self):
        self.ip_forward = Path("/proc/sys/net/ipv4/ip_forward").read_text()
        self.tables = self._tables()
        self.links = self._links()

    @staticmethod
    def _tables() -> set:
        if not shutil.which("nft"):
            return set()
        out = _run(["nft", "list", "tables"], 20, check=False).stdout
        return {ln.strip() for ln in out.splitlines() if ln.startswith("table ")}

    @staticmethod
    def _links() -> set:
        return set(os.listdir("/sys/class/net"))

    def restore(self) -> None:
        Path("/proc/sys/net/ipv4/ip_forward").write_text(self.ip_forward)
        for table in self._tables() - self.tables:
            _run(["nft", "delete", *table.split()[1:]], 20, check=False)
        for link in self._links() - self.links:
            if link == "docker0" or link.startswith(("br-", "veth")):
                _run(["ip", "link", "delete", link], 20, check=False)


@pytest.fixture(scope="module")
def engine(tmp_path_factory):
    """The running engine, or one started here (and stopped, its changes undone)."""
    compose_cmd = _compose_cmd()
    if not shutil.which("docker") or compose_cmd is None:
        pytest.skip("no container engine: docker and docker-compose are not installed "
                    "(apt-get install docker.io docker-compose mmdebstrap)")
    if _docker_ok():
        yield compose_cmd
        return
    if not shutil.which("dockerd") or os.geteuid() != 0:
        pytest.skip("no container engine: no daemon running, and none can be started here (dockerd as root)")
    state = HostState()
    log = tmp_path_factory.mktemp("dockerd") / "dockerd.log"
    with open(log, "w") as f:
        daemon = subprocess.Popen(["dockerd", "--iptables=false", "--ip-forward=false"], stdout=f,
                                  stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while not _docker_ok():
            if daemon.poll() is not None or time.monotonic() > deadline:
                lines = log.read_text().strip().splitlines() or ["(no output)"]
                pytest.skip(f"no container engine: dockerd did not start: {lines[-1][-300:]}")
            time.sleep(0.5)
        yield compose_cmd
    finally:
        daemon.send_signal(signal.SIGTERM)  # it stops its containerd and containers
        try:
            daemon.wait(60)
        except subprocess.TimeoutExpired:
            daemon.kill()
            daemon.wait()
        state.restore()


@pytest.fixture(scope="module")
def image(engine):
    """The Dockerfile's image, on the FROM image or its stand-in; (compose
    command, image size in bytes)."""
    base = next(ln.split()[1] for ln in (ROOT / "Dockerfile").read_text().splitlines() if ln.startswith("FROM "))
    if _run(["docker", "image", "inspect", base], 30, check=False).returncode:
        try:
            pulled = _run(["docker", "pull", base], 300, check=False).returncode == 0
        except subprocess.TimeoutExpired:
            pulled = False
        if not pulled:
            _run([str(ROOT / "docker" / "build-base-image.sh")], BUILD_TIMEOUT_S)
    before = _run(["docker", "image", "inspect", "-f", "{{.Id}}", IMAGE], 30, check=False).stdout.strip()
    # the host's network for the build: the lock's wheels come from the package index
    _run(["docker", "build", "--network", "host", "-t", IMAGE, str(ROOT)], BUILD_TIMEOUT_S)
    if before and before != _run(["docker", "image", "inspect", "-f", "{{.Id}}", IMAGE], 30).stdout.strip():
        _run(["docker", "image", "rm", before], 60, check=False)  # the image this build replaced (untagged now)
    size = int(_run(["docker", "image", "inspect", "-f", "{{.Size}}", IMAGE], 30).stdout)
    print(f"\nimage {IMAGE}: {size / 1e6:.0f} MB")
    return engine, size


class Stack:
    """One compose project (a name of its own), removed on leaving."""

    def __init__(self, compose_cmd: list, file: str, results: Path, name: str, override: Path | None = None):
        self.cmd = [*compose_cmd, "-f", str(ROOT / file), *(["-f", str(override)] if override else [])]
        self.env = {**os.environ, "COMPOSE_PROJECT_NAME": name, "DISKF_RESULTS": str(results),
                    "DISKF_UID": str(os.getuid()), "DISKF_GID": str(os.getgid())}

    def __call__(self, *args, timeout: float = RUN_TIMEOUT_S, check: bool = True) -> subprocess.CompletedProcess:
        return _run([*self.cmd, *args], timeout, check=check, env=self.env)

    def container(self, service: str) -> str:
        return self("ps", "-q", service).stdout.strip()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self("down", "--volumes", "--timeout", str(STOP_GRACE_S), check=False)


def _project(tag: str) -> str:
    return f"diskf-ci-{os.getpid()}-{tag}"


def _state(cid: str) -> dict:
    return json.loads(_run(["docker", "inspect", "-f", "{{json .State}}", cid], 30).stdout)


@pytest.mark.parametrize("file", sorted(FILES))
def test_the_documented_demo_completes_with_the_engines_estimates(image, file, tmp_path):
    """docker/demo.sh FILE: the world's table, its exit status 0, and the
    results file it wrote: complete, every agent's estimate and fused set the
    engine's bit for bit for the same seed."""
    compose_cmd, _ = image
    results = tmp_path / "results"
    name = _project("demo")
    env = {**os.environ, "COMPOSE_PROJECT_NAME": name, "DISKF_RESULTS": str(results)}
    began = time.monotonic()
    with Stack(compose_cmd, file, results, name):  # removed even if the script is killed
        done = _run([str(ROOT / "docker" / "demo.sh"), file], RUN_TIMEOUT_S, check=False, env=env)
    print(f"\n{file}: docker/demo.sh took {time.monotonic() - began:.1f} s")
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.search(r"MAE\(state\)\s+\d", done.stdout), done.stdout
    stem = Path(compose.WORLD_EXTRA[1] if file == "docker-compose.yml" else compose.HOSTS_WORLD_EXTRA[1]).stem
    summary = json.loads((results / f"{stem}.json").read_text())
    doc = json.loads((results / f"{stem}-estimates.json").read_text())
    assert doc["complete"] and doc["missing_agent_ticks"] == 0
    assert doc["status"] == "exact", doc["reason"]  # the world's own replay on the engine agrees
    for written in (summary, doc):  # the provenance up writes, from inside the containers
        prov = written["provenance"]
        assert prov["status"] == "exact" and prov["seeds"] == [compose.SEED] and prov["ticks"] == compose.TICKS
    assert_engine_bit_for_bit(doc, FILES[file], compose.TICKS, compose.SEED)


def _on_the_clock(file: str, tmp_path: Path) -> Path:
    """An override: the same run on the wall clock (``--rate``), the world
    saying which tick it is on, so that every stop lands mid-run."""
    services = yaml.safe_load((ROOT / file).read_text())["services"]
    clocked = {name: {"command": [*s["command"], "--rate", str(RATE_HZ),
                                  *(["--progress", "lines"] if name == "world" else [])]}
               for name, s in services.items() if name == "world" or name.startswith(("agent-", "host-"))}
    path = tmp_path / "clocked.yml"
    path.write_text(yaml.safe_dump({"services": clocked}))
    return path


def _wait_for_tick(stack: Stack, k: int, timeout: float = 120) -> None:
    world = stack.container("world")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ticks = [int(m) for m in re.findall(r"^tick (\d+) ", _run(["docker", "logs", world], 30).stdout, re.M)]
        if ticks and max(ticks) >= k:
            return
        assert _state(world)["Running"], _run(["docker", "logs", world], 30).stderr[-2000:]
        time.sleep(0.3)
    raise AssertionError(f"the world did not reach tick {k} in {timeout:g} s")


def _stops(project: str, since: float) -> dict:
    """{service: (seconds from SIGTERM to exit or None, exit status, the
    signals sent)} of the project's containers that ended after ``since``,
    from the engine's events."""
    until = time.time() + 1
    out = _run(["docker", "events", "--since", f"{since:.3f}", "--until", f"{until:.3f}", "--format", "{{json .}}",
                "--filter", f"label=com.docker.compose.project={project}", "--filter", "type=container"], 60).stdout
    seen = {}
    for line in out.splitlines():
        e = json.loads(line)
        attrs = e["Actor"]["Attributes"]
        if e["Action"] not in ("kill", "die"):
            continue
        c = seen.setdefault(attrs["com.docker.compose.service"], {"signals": [], "term": None})
        if e["Action"] == "kill":
            c["signals"].append(int(attrs["signal"]))
            if int(attrs["signal"]) == signal.SIGTERM and c["term"] is None:
                c["term"] = e["timeNano"] / 1e9
        elif e["Action"] == "die":
            c["took"] = e["timeNano"] / 1e9 - c["term"] if c["term"] is not None else None
            c["status"] = int(attrs["exitCode"])
    return {s: (c.get("took"), c.get("status"), c["signals"]) for s, c in seen.items()}


RATE_HZ = 5  # 200 ticks take 40 s: every stop below lands mid-run
# stopped one at a time mid-run (docker stop: SIGTERM, SIGKILL after 10 s), in this order; `down` then stops the
# rest together (agents or hosts first, then what they depend on)
ONE_BY_ONE = {"docker-compose.yml": ("agent-1", "agent-2", "agent-3", "agent-4"),
              "docker-compose.hosts.yml": ("host-a", "router-b")}
# exit status on SIGTERM (diskf_mesh.mesh.process.stopping): the world writes its results, marked interrupted, and exits
# 3 (incomplete), or 4 where real time had missed too many deadlines before (these runs are on the clock)
STOPPED = {"world": (3, 4), "router": (0,), "agent": (128 + signal.SIGTERM,), "host": (128 + signal.SIGTERM,)}
DOWN_WITHIN_S = 5.0  # several containers at once: the engine's own work shares the 2 cores; far from the 10 s grace


@pytest.mark.parametrize("file", sorted(FILES))
def test_every_service_stops_on_sigterm_mid_run_without_sigkill(image, file, tmp_path):
    """Mid-run, SIGTERM to services one at a time, then ``down``: every
    process stopped alone exits within 2 s of its SIGTERM (the engine's own
    event times), those of ``down`` well before the grace ends, each with its
    documented status; none is sent SIGKILL."""
    compose_cmd, _ = image
    results = tmp_path / "results"
    results.mkdir()
    project = _project("stop")
    with Stack(compose_cmd, file, results, project, _on_the_clock(file, tmp_path)) as stack:
        stack("up", "--detach")
        _wait_for_tick(stack, 10)
        since = time.time()
        for service in ONE_BY_ONE[file]:
            _run(["docker", "stop", "-t", str(STOP_GRACE_S), stack.container(service)], STOP_GRACE_S + 30)
        assert _state(stack.container("world"))["Running"]  # still mid-run
        stack("down", "--volumes", "--timeout", str(STOP_GRACE_S))
    stops = _stops(project, since)
    print(f"\n{file}: SIGTERM to exit " + ", ".join(f"{s} {t if t is None else round(t, 2)} s (exit {rc})"
                                                    for s, (t, rc, _) in sorted(stops.items())))
    services = set(yaml.safe_load((ROOT / file).read_text())["services"]) - {"credentials"}
    assert set(stops) == services, stops
    for s, (took, status, signals) in stops.items():
        assert signals == [signal.SIGTERM] and status in STOPPED[s.split("-")[0]], (s, status, signals)
        assert took < (STOP_WITHIN_S if s in ONE_BY_ONE[file] else DOWN_WITHIN_S), (s, took)
    interrupted = json.loads(next(results.glob("*-estimates.json")).read_text())
    assert not interrupted["complete"] and "SIGTERM" in interrupted["ended_early"]


@pytest.mark.parametrize("delay", [0.0, 0.5])
def test_a_container_stopped_while_it_starts_exits_at_once(image, delay):
    """SIGTERM while the process starts: under the init the compose files use
    (``docker run --init``) it ends at once, with 143 while it still imports
    (no handler yet) or the world's own SIGTERM status once its handler is in
    (3: the run ended before it began), where as PID 1 alone it would ignore
    the signal until SIGKILL."""
    cid = _run(["docker", "run", "--detach", "--init", IMAGE, "python", "-m", "sim.world", "--scenario", "dynamic",
                "--algorithm", "diskf", "--run-id", "start", "--insecure"], 60).stdout.strip()
    try:
        time.sleep(delay)
        began = time.monotonic()
        _run(["docker", "stop", "-t", str(STOP_GRACE_S), cid], STOP_GRACE_S + 30)
        took = time.monotonic() - began
        state = _state(cid)
    finally:
        _run(["docker", "rm", "--force", cid], 60, check=False)
    assert state["ExitCode"] in (128 + signal.SIGTERM, *STOPPED["world"]) and not state["OOMKilled"], state
    assert took < STOP_WITHIN_S, took
