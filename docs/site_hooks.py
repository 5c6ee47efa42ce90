"""MkDocs hooks of the documentation site (mkdocs.yml).

A page of ``docs/`` that ``mkdocs.yml``'s nav does not list goes under
"More" at its end, so every page is in the navigation.

A page whose first line is ``<!-- mirror: PATH -->`` shows the repository's
file PATH (relative to the page) instead of its own text: the front page is
the README, the changelog page CHANGELOG.md.

Links are written for reading the repository (on a forge or in a clone). In
the site, a link to a file inside ``docs/`` is made relative to the page; a
link to a file outside it (``examples/``, ``LICENSE``, a schema) becomes the
path as text, after a check that the file exists: a link to nothing is a
warning, which ``mkdocs build --strict`` turns into a failure.
"""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path, PurePosixPath

log = logging.getLogger("mkdocs.plugins.diskf_mesh")

MIRROR = re.compile(r"\A<!-- mirror: (\S+) -->")
FENCE = re.compile(r"^(```.*?^```)", re.M | re.S)
LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")


def on_config(config):
    listed = set(_pages(config["nav"] or []))
    docs = Path(config["docs_dir"])
    extra = sorted(p.relative_to(docs).as_posix() for p in docs.rglob("*.md"))
    excluded = config["exclude_docs"]
    extra = [p for p in extra if p not in listed and not (excluded and excluded.match_file(p))]
    if extra and config["nav"] is not None:
        config["nav"].append({"More": extra})
    return config


def _pages(nav):
    """Every page path a nav lists (its entries: a path, {title: path} or {title: [entries]})."""
    for item in nav:
        if isinstance(item, str):
            yield item
        elif isinstance(item, dict):
            for v in item.values():
                yield from ([v] if isinstance(v, str) else _pages(v))


def on_page_markdown(markdown: str, page, config, files) -> str:
    docs = Path(config["docs_dir"]).resolve()
    page_dir = (docs / page.file.src_uri).parent
    source_dir = page_dir
    mirror = MIRROR.match(markdown)
    if mirror:
        source = (page_dir / mirror.group(1)).resolve()
        markdown, source_dir = source.read_text(), source.parent
    parts = FENCE.split(markdown)  # odd parts: fenced code, left alone
    for i in range(0, len(parts), 2):
        parts[i] = LINK.sub(lambda m: _link(m, source_dir, page_dir, docs, page.file.src_uri), parts[i])
    return "".join(parts)


def _link(m: re.Match, source_dir: Path, page_dir: Path, docs: Path, page: str) -> str:
    bang, text, target = m.groups()
    if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
        return m.group(0)  # a URL, an anchor of the page, a site-absolute path: as it is
    path, _, anchor = target.partition("#")
    where = (source_dir / path).resolve()
    if not where.exists():
        log.warning(f"{page}: link to {target!r}, which does not exist")
        return m.group(0)
    if where == docs or docs in where.parents:
        rel = PurePosixPath(os.path.relpath(where, page_dir)).as_posix()
        return f"{bang}[{text}]({rel}{'#' + anchor if anchor else ''})"
    shown = where.relative_to(docs.parent).as_posix() + ("/" if where.is_dir() else "")
    return text if shown.rstrip("/") in text else f"{text} (`{shown}`)"
