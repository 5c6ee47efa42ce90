"""``pip install .`` installs one top-level import package, ``diskf_mesh``
(the repository's sim/ and agents/ go inside it), and the mesh runs from
that install in an empty folder."""
from __future__ import annotations

import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(out)],
                          capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        pytest.skip(f"cannot build a wheel here (no package index?): {done.stderr.strip().splitlines()[-1:]}")
    (whl,) = out.glob("diskf_mesh-*.whl")
    return whl


@pytest.mark.slow
def test_the_wheel_has_one_top_level_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"diskf_mesh"}
    assert "diskf_mesh/_apps/sim/world.py" in names and "diskf_mesh/_apps/agents/agent.py" in names
    assert "diskf_mesh/py.typed" in names
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("/METADATA"))).decode()
    assert "Classifier: Programming Language :: Python :: 3.11" in meta and "Project-URL: Paper" in meta
    assert "Author: The diskf-mesh authors" in meta or "diskf-mesh authors" in meta


@pytest.mark.slow
@pytest.mark.mesh
def test_up_runs_from_an_install_in_an_empty_folder(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    # the dependencies from this interpreter's site-packages, after the venv's own (where the wheel goes)
    Path(purelib, "zz-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--ignore-installed", str(wheel)], check=True, timeout=300)
    site = Path(purelib)
    assert not (site / "sim").exists() and not (site / "agents").exists()
    env = {"PATH": f"{venv / 'bin'}:/usr/bin:/bin", "HOME": str(tmp_path)}
    assert subprocess.run([str(py), "-c", "import sim"], cwd=tmp_path, env=env, capture_output=True).returncode != 0
    run = tmp_path / "empty"
    run.mkdir()
    done = subprocess.run([str(venv / "bin" / "diskf-mesh"), "up", "--ticks", "20", "--json", "r.json", "--quiet"],
                          cwd=run, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert (run / "r.json").exists()


def test_the_version_has_one_source():
    """``diskf_mesh.__version__`` is the version: pyproject.toml reads it, the
    installed metadata carries it, CITATION.cff and the changelog's latest
    release name it, and the changelog keeps an Unreleased section on top."""
    import importlib.metadata
    import re
    import tomllib

    import yaml

    from diskf_mesh import __version__

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "diskf_mesh.__version__"}
    assert importlib.metadata.version("diskf-mesh") == __version__
    assert str(yaml.safe_load((ROOT / "CITATION.cff").read_text())["version"]) == __version__
    releases = re.findall(r"^## (\S+)(?: - (\d{4}-\d{2}-\d{2}))?$", (ROOT / "CHANGELOG.md").read_text(), re.M)
    assert releases[0] == ("Unreleased", "")
    assert releases[1][0] == __version__ and releases[1][1], "the latest release, with its date"
