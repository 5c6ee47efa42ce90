"""CPU time of the simulated network's batched agent steps inside one run.

Runs ``diskf-mesh up --network simulated --scenario random-geometric
--agents N --ticks K`` in this process with ``time.process_time`` around
``Steps._fuse`` and ``Steps._local`` (``mesh.protocol.estimator``), and
prints the run's CPU time and the two steps' share of it. Not a test;
compare trees by running each in turn (``PYTHONPATH=TREE``) in one shell
loop.

    python benchmarks/steps_bench.py [--agents 1000] [--ticks 20]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import time

from diskf_mesh.cli.main import main as cli
from diskf_mesh.mesh.protocol import estimator


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, default=1000)
    ap.add_argument("--ticks", type=int, default=20)
    a = ap.parse_args(argv)
    spent = {"fuse": 0.0, "local": 0.0}

    def timed(name, step):
        def run(self, batch):
            t = time.process_time()
            try:
                return step(self, batch)
            finally:
                spent[name] += time.process_time() - t
        return run

    estimator.Steps._fuse = timed("fuse", estimator.Steps._fuse)
    estimator.Steps._local = timed("local", estimator.Steps._local)
    t0 = time.process_time()
    with contextlib.redirect_stdout(io.StringIO()):
        status = cli(["up", "--network", "simulated", "--scenario", "random-geometric", "--agents", str(a.agents),
                      "--ticks", str(a.ticks)])
    total = time.process_time() - t0
    print(f"{a.agents} agents x {a.ticks} ticks: {total:.2f} s CPU in all, Steps fusion {spent['fuse']:.2f} s, "
          f"local steps {spent['local']:.2f} s, exit {status}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
