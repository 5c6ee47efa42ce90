"""``Child``: one process of a run as the launcher starts and watches it
(its name, command line, log file and the identities handed to it)."""
from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Child:
    name: str
    argv: list
    log: Path
    proc: subprocess.Popen | None = None
    identities: tuple = ()  # the identities it is handed (``Launcher``'s ``keys``), on its standard input

    def last_error_line(self) -> str:
        try:
            lines = [ln for ln in self.log.read_text(errors="replace").splitlines() if ln.strip()]
        except OSError:
            return ""
        return lines[-1] if lines else ""
