"""``--help`` as plain text for a user: a command's description without
code markup or the package's internal names, and the exit statuses every
command may end with.

The descriptions are the command modules' docstrings, written for both
readers; ``plain`` keeps what a user needs: ``python -m sim.world`` becomes
``diskf-mesh world``, a constant becomes its value, a module or class name
goes, and the paragraphs are filled again.
"""
from __future__ import annotations

import argparse
import re
import sys
import textwrap

from diskf_mesh.core import exits

WIDTH = 79
_PROCESSES = {"sim.world": "diskf-mesh world", "agents.agent": "diskf-mesh agent", "sim.router": "diskf-mesh router",
              "sim.host": "diskf-mesh host", "sim.launcher": "diskf-mesh up"}
_MODULE = re.compile(r"^(python -m )?(diskf_mesh|sim|agents|mesh|data|engine|core|scenario|credentials|estimators|"
                     r"recording|studies|live|cli)(\.\w+)+(\(\))?$")
_CONSTANT = re.compile(r"^[A-Z][A-Z0-9_]*_[A-Z0-9_]+$")
_CLASS = re.compile(r"^[A-Z][a-z]+(?:[A-Z][a-z]+)*(\.\w+)?$")
_DROP = "\0"

EXIT_STATUSES = (
    (exits.OK, "success (a mesh run: exact, or as planned with only the faults it was given)"),
    (exits.FAILED, "a process of the run failed (one line says which and why), or a replay differs from its run"),
    (exits.BAD_INPUT, "bad input: one 'error: <field>: <message>' line, nothing written"),
    (exits.INCOMPLETE, "a mesh run missed agent-ticks beyond --allow-missing"),
    (exits.TOO_MANY_MISSES, "a real-time run missed deadlines beyond --max-miss-rate"),
    (exits.DEGRADED, "a mesh run fused fewer messages than planned (--allow-degraded accepts it)"),
    (exits.DIVERGED, "a reported estimate that the engine does not reproduce"),
    (exits.RECORDING_FAILED, "the run's recording could not be written whole (e.g. a full disk)"),
    (exits.UNVERIFIABLE, "a mesh run reported agent-ticks the engine cannot verify (built on a report that did not "
                         "come); only --accept-unverifiable accepts it"),
    (130, "interrupted (Ctrl-C): every process it started is stopped"),
    (141, "its output pipe was closed (e.g. '| head')"),
    (143, "terminated (SIGTERM): every process it started is stopped"),
)


def exit_statuses() -> str:
    """The epilog of every command's --help."""
    rows = "\n".join(textwrap.fill(what, WIDTH, initial_indent=f"  {code:>3}  ", subsequent_indent=" " * 7)
                     for code, what in EXIT_STATUSES)
    return f"exit status:\n{rows}"


def _constant(name: str) -> str | None:
    """The value of an upper-case constant of a loaded command module."""
    for mod in list(sys.modules.values()):
        if getattr(mod, "__name__", "").startswith(("diskf_mesh", "sim", "agents")):
            value = getattr(mod, name, None)
            if isinstance(value, (int, float, str)) and not isinstance(value, bool):
                return str(value)
    return None


def _span(match: re.Match) -> str:
    code = match.group(1)
    module = code.removeprefix("python -m ")
    if module in _PROCESSES:
        return _PROCESSES[module]
    if code == "Params()":
        return "the default settings"
    if _CONSTANT.match(code):
        return _constant(code) or _DROP
    if _MODULE.match(code) or _CLASS.match(code):
        return _DROP
    return code


def _tidy(text: str) -> str:
    """Text with the dropped names gone, and the punctuation around them."""
    text = re.sub(r"\(\s*" + _DROP + r"\s*\)", "", text)
    text = re.sub(_DROP + r"\s*[:;,]\s*", "", text)
    text = re.sub(r"\s*[,;]\s*" + _DROP, "", text)
    text = re.sub(r"\s*" + _DROP, "", text)
    text = re.sub(r"\(\s*\)", "", text)
    text = re.sub(r"\(\s+", "(", text)
    text = re.sub(r"\s+\)", ")", text)
    text = re.sub(r"\s+([,.;:])", r"\1", text)
    return re.sub(r"[ \t]{2,}", " ", text)


def _names(text: str) -> str:
    """``text`` with its code spans and bare module paths resolved (a
    process becomes its command, a constant its value; the rest dropped)."""
    text = re.sub(r"``([^`]+)``", _span, text)
    text = re.sub(r"(?<![`\w])`([^`\n]+)`(?![`\w])", _span, text)
    text = re.sub(r"\((?:engine|mesh|core|data|studies|recording|live|cli|estimators)\.[a-z_][\w.]*\w\)", "", text)
    return re.sub(r"(?<![\w/.-])((?:python -m )?(?:diskf_mesh|sim|agents)\.[a-z_][\w.]*\w)",
                  lambda m: _span(re.match(r"(.*)", m.group(1))), text)


def plain_line(text: str | None) -> str | None:
    """One option's help as plain text."""
    if not text or text is argparse.SUPPRESS:
        return text
    return _tidy(_names(text)).strip()


def plain(doc: str | None, width: int = WIDTH) -> str | None:
    """A docstring as plain text for --help."""
    if not doc:
        return doc
    text = _names(doc)
    out = []
    for para in re.split(r"\n\s*\n", text.strip("\n")):
        lines = para.splitlines()
        if any(line.startswith((" ", "\t")) for line in lines):  # an indented block: a table or a command
            out.append(_tidy_block(lines))
        else:
            out.append(textwrap.fill(_tidy(" ".join(line.strip() for line in lines)), width))
    return "\n\n".join(p for p in out if p.strip())


def _tidy_block(lines: list[str]) -> str:
    return "\n".join(_tidy(line) if _DROP in line else line.rstrip() for line in lines)
