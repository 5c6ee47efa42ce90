"""The documentation site: ``mkdocs build --strict`` passes (every link and
anchor resolves, every page is in the navigation, the API reference builds
from the docstrings), the front page is the README, and the gallery shows
every figure in docs/figures."""
from __future__ import annotations

import importlib.util
import logging
import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert done.returncode == 0, done.stderr
    return out


def test_the_site_builds_strict(site):
    pages = {p.relative_to(DOCS).with_suffix("").as_posix() for p in DOCS.glob("*.md")} - {"index"}
    assert {p for p in pages if (site / p / "index.html").exists()} == pages
    assert not (site / "site_hooks.py").exists()
    reference = (site / "reference" / "index.html").read_text()
    for name in ("load_scenario", "Network", "Agent", "Estimate", "InputError", "Estimator", "Exchanged"):
        assert f'id="diskf_mesh.' in reference and re.search(rf'id="diskf_mesh\.[\w.]*\b{name}"', reference), name


def test_the_front_page_is_the_readme_with_its_links_into_the_site(site):
    front = (site / "index.html").read_text()
    readme = (ROOT / "README.md").read_text()
    title = readme.splitlines()[0].lstrip("# ")
    assert f">{title}<" in front and "Table II next to the paper" in front
    assert '<img alt="error against communication range" src="figures/error_vs_range.png"' in front
    assert 'href="api/#one-tick-at-a-time"' in front and 'href="docs/' not in front


def test_the_gallery_shows_every_figure_once():
    shown = re.findall(r"!\[[^\]]*\]\(figures/([^)]+)\)", (DOCS / "gallery.md").read_text())
    assert sorted(shown) == sorted(p.name for p in (DOCS / "figures").iterdir())


def _hooks():
    spec = importlib.util.spec_from_file_location("site_hooks", DOCS / "site_hooks.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_links_out_of_docs_become_paths_and_a_link_to_nothing_warns(caplog):
    hooks = _hooks()
    page = SimpleNamespace(file=SimpleNamespace(src_uri="api.md"))
    config = {"docs_dir": str(DOCS)}
    text = ("[examples/](../examples) [the plugin](../examples/estimator-plugin) [formats](formats.md#provenance) "
            "![f](figures/realtime.png) [web](https://zenoh.io) [here](#calls)\n```\n[x](../nothing)\n```\n")
    out = hooks.on_page_markdown(text, page, config, None)
    assert out.startswith("examples/ the plugin (`examples/estimator-plugin/`) [formats](formats.md#provenance) "
                          "![f](figures/realtime.png) [web](https://zenoh.io) [here](#calls)")
    assert "[x](../nothing)" in out  # fenced code is left alone
    with caplog.at_level(logging.WARNING, logger="mkdocs.plugins.diskf_mesh"):
        hooks.on_page_markdown("[gone](../no/such/file.py)", page, config, None)
    assert "link to '../no/such/file.py', which does not exist" in caplog.text
    mirrored = hooks.on_page_markdown("<!-- mirror: ../README.md -->\n", SimpleNamespace(
        file=SimpleNamespace(src_uri="index.md")), config, None)
    assert "](docs/" not in mirrored and "[docs/api.md](api.md)" in mirrored


def test_a_page_the_nav_does_not_list_goes_under_more(tmp_path):
    for name in ("index.md", "a.md", "b.md"):
        (tmp_path / name).write_text("# page\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "c.md").write_text("# page\n")
    config = {"docs_dir": str(tmp_path), "exclude_docs": None,
              "nav": [{"Home": "index.md"}, {"Use": [{"A": "a.md"}]}]}
    assert _hooks().on_config(config)["nav"][-1] == {"More": ["b.md", "sub/c.md"]}
    config["nav"] = [{"Home": "index.md"}, {"Use": [{"A": "a.md"}, "b.md", "sub/c.md"]}]
    assert _hooks().on_config(config)["nav"] == [{"Home": "index.md"}, {"Use": [{"A": "a.md"}, "b.md", "sub/c.md"]}]
