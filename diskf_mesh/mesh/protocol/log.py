"""One-line messages of a mesh process on stderr, prefixed with who says them."""
from __future__ import annotations

import sys


class Log:
    def __init__(self, who: str, stream=None):
        self.who = who
        self.stream = stream
        self._said = set()

    def _write(self, line: str) -> None:
        print(line, file=self.stream or sys.stderr, flush=True)

    def info(self, msg: str) -> None:
        self._write(f"{self.who}: {msg}")

    def error(self, msg: str) -> None:
        self._write(f"error: {self.who}: {msg}")

    def once(self, key, msg: str) -> None:
        """Say ``msg`` the first time ``key`` comes up, never again."""
        if key not in self._said:
            self._said.add(key)
            self.info(msg)
