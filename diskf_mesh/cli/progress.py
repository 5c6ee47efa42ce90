"""How far a long command is: a tqdm bar on a terminal, else one line per
stage on standard error (``report: [3/12] Table I: compensation: 4.1 s``);
nothing with ``--quiet``."""
from __future__ import annotations

import sys
import time


class Progress:
    """Stages of ``command``, ``total`` of them (known at the first
    ``step`` if not before)."""

    def __init__(self, command: str, quiet: bool = False, total: int | None = None, unit: str = "stage"):
        self.command, self.total, self.unit, self.done = command, total, unit, 0
        self.lines = not quiet and not sys.stderr.isatty()
        self.bars = not quiet and not self.lines
        self._bar = None
        self._said = time.monotonic()  # when ``status`` last showed something (or the start)

    def _shown(self):
        if self.bars and self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=self.command, unit=self.unit, file=sys.stderr)
        return self._bar

    def note(self, text: str) -> None:
        """A line that is no stage (what runs, at the start)."""
        if self.bars:
            self._shown().write(f"{self.command}: {text}", file=sys.stderr)
        elif self.lines:
            print(f"{self.command}: {text}", file=sys.stderr, flush=True)

    def step(self, title: str = "", seconds: float | None = None, n: int = 1) -> None:
        """``n`` stages done, the last one ``title`` (in ``seconds``)."""
        self.done += n
        if self.bars:
            bar = self._shown()
            bar.set_postfix_str(title[:40], refresh=False)
            bar.update(n)
        elif self.lines:
            took = f": {seconds:.1f} s" if seconds is not None else ""
            print(f"{self.command}: [{self.done}/{self.total}] {title}{took}", file=sys.stderr, flush=True)

    def status(self, text: str, every: float = 10.0) -> None:
        """How far the current stage is (``text``), at most once every
        ``every`` seconds (the first ``every`` seconds after the start): the
        bar's postfix on a terminal, else a line."""
        now = time.monotonic()
        if not (self.bars or self.lines) or now - self._said < every:
            return
        self._said = now
        if self.bars:
            self._shown().set_postfix_str(text[:40])
        else:
            print(f"{self.command}: {text}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
