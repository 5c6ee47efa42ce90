"""A benchmark script of this tree beside the same script of an earlier commit, in one invocation.

    python benchmarks/versus.py --baseline REV [--rounds 3] -- benchmarks/engine_bench.py --quick
    python benchmarks/versus.py --baseline REV -- benchmarks/agent_bench.py --repeat 3

REV is checked out into a temporary git worktree; each round runs the
baseline's copy of the script and then this tree's (each with its own code
first on PYTHONPATH), so both see the same machine load. Prints every
round's output, labelled. On a shared machine only such side-by-side
figures compare: quote the best (or median) of the rounds, not one run.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def run(tree: Path, script: list) -> str:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, str(tree / script[0]), *script[1:]], cwd=tree, env=env,
                          capture_output=True, text=True)
    return done.stdout + (f"[exit {done.returncode}] {done.stderr.strip().splitlines()[-1:]}" if done.returncode else "")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", required=True, help="the earlier commit (any git revision)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("script", nargs=argparse.REMAINDER, help="-- SCRIPT [ARGS]: a path relative to the tree")
    args = ap.parse_args()
    script = args.script[1:] if args.script[:1] == ["--"] else args.script
    if not script:
        ap.error("give the script after --")
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "baseline"
        subprocess.run(["git", "-C", str(HERE), "worktree", "add", "-q", "--detach", str(base), args.baseline],
                       check=True)
        try:
            for r in range(1, args.rounds + 1):
                for label, tree in (("baseline " + args.baseline, base), ("this tree", HERE)):
                    print(f"## round {r}: {label}\n{run(tree, script)}", flush=True)
        finally:
            subprocess.run(["git", "-C", str(HERE), "worktree", "remove", "--force", str(base)], check=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
