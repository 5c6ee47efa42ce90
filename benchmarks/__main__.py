"""The benchmarks from one entry point (run from the repository's root):

    python -m benchmarks                 what each script measures (its docstring's first sentence)
    python -m benchmarks NAME [ARGS]     run benchmarks/NAME.py with ARGS

benchmarks/README.md has the same list with the page each one writes.
"""
from __future__ import annotations

import ast
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def scripts() -> dict:
    """{name: first sentence of its docstring} of every script here."""
    out = {}
    for path in sorted(HERE.glob("*.py")):
        if path.name.startswith("_"):
            continue
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        first = " ".join(doc.split("\n\n")[0].split()).replace("``", "")
        out[path.stem] = first.split(". ")[0].rstrip(".") + "."
    return out


def main(argv) -> int:
    found = scripts()
    if not argv or argv[0] in ("-h", "--help"):
        width = max(map(len, found))
        print(__doc__.strip().splitlines()[0])
        for name, what in found.items():
            print(f"  {name:<{width}}  {what}")
        return 0
    name = argv[0].removesuffix(".py")
    if name not in found:
        import difflib

        close = difflib.get_close_matches(name, found, n=1)
        print(f"error: no benchmark {name}" + (f" (did you mean {close[0]}?)" if close else ""), file=sys.stderr)
        return 2
    script = HERE / f"{name}.py"
    os.execv(sys.executable, [sys.executable, str(script), *argv[1:]])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
