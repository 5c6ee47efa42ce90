"""docs/costs.md (and docs/costs.json, its numbers) from one command: what
the commands that the README and the docs name cost, wall-clock and CPU
time, each run once on this machine, one after the other in one invocation.

    python benchmarks/costs.py [--only demo,report,...] [--all]

Without ``--only`` it measures the entries marked default (a few minutes of
CPU); ``--all`` adds the long ones (the held-out suite, the 1,000-agent
simulated run, every test: about an hour). An entry not measured keeps its
figures of an earlier run, with its own date and load. Every figure names
the machine and the load average while it ran: a figure measured while
other work shared the cores says so. The README and the docs link here
instead of stating a cost (``tests/test_costs.py`` checks that every such
link's words are this file's figures).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from performance import hardware  # noqa: E402 (the same machine line as performance.md)

JSON = ROOT / "docs" / "costs.json"
MARKDOWN = ROOT / "docs" / "costs.md"
CLI = ["{python}", "-m", "diskf_mesh.cli.main"]


@dataclass(frozen=True)
class Cost:
    key: str
    what: str
    argv: tuple
    default: bool = True


COSTS = (
    Cost("demo", "the demo: the world and nine agent processes of Scenario 2, 200 ticks",
         (*CLI, "up", "--scenario", "dynamic", "--ticks", "200", "--json", "{tmp}/r.json", "--quiet")),
    Cost("table-ii", "Table II: every estimator, three topologies, 20 seeds",
         (*CLI, "experiment", "--scenario", "quadrants", "--seeds", "20", "--quiet")),
    Cost("report", "every study of the paper and its figures, 20 seeds, one process per core",
         (*CLI, "report", "--out", "{tmp}", "--quiet")),
    Cost("report-heldout", "the report and the held-out suite (every estimator on 235 cases), one process per core",
         (*CLI, "report", "--heldout", "--out", "{tmp}", "--quiet"), default=False),
    Cost("tour", "500 agents on the simulated network, 20 ticks (the README's tour)",
         (*CLI, "up", "--network", "simulated", "--scenario", "random-geometric", "--agents", "500", "--ticks",
          "20", "--json", "{tmp}/r.json", "--quiet")),
    Cost("simulated-1000", "1,000 agents on the simulated network, 20 ticks",
         (*CLI, "up", "--network", "simulated", "--scenario", "random-geometric", "--agents", "1000", "--ticks",
          "20", "--json", "{tmp}/r.json", "--quiet"), default=False),
    Cost("tests-quick", "the quick tests (`-m quick`)",
         ("{python}", "-m", "pytest", "-q", "-m", "quick", "-p", "no:cacheprovider")),
    Cost("tests", "every test (what CI runs)", ("{python}", "-m", "pytest", "-q", "-p", "no:cacheprovider"),
         default=False),
)
BY_KEY = {c.key: c for c in COSTS}


def shown(argv) -> str:
    """The command as a user types it."""
    words = [w.replace("{tmp}", "DIR") for w in argv]
    if words[:3] == ["{python}", "-m", "diskf_mesh.cli.main"]:
        words = ["diskf-mesh", *words[3:]]
    elif words[:1] == ["{python}"]:
        words = ["python", *words[1:]]
    return " ".join(w for w in words if w not in ("--quiet", "-p", "no:cacheprovider"))


def duration(seconds: float) -> str:
    """'40 s', '4.5 min', '41 min'."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = seconds / 60
    return f"{minutes:.1f} min" if minutes < 10 else f"{minutes:.0f} min"


def summary(row: dict | None) -> str:
    """An entry's figures as the README and the docs quote them (the words
    of a link to this file): '70 s, 139 s of CPU'."""
    if row is None:
        return "not measured yet"
    if row.get("cpu_s") is None:
        return f"about {duration(row['wall_s'])}"
    return f"{duration(row['wall_s'])}, {duration(row['cpu_s'])} of CPU"


PLAIN = ("costs", "costs.md", "docs/costs.md")  # a link's words that only point to the page
LINK = re.compile(r"\[([^\]]*)\]\(((?:docs/)?costs\.md#([a-z0-9-]+))\)")


def relink(text: str, doc: dict) -> str:
    """``text`` with the words of every link to an entry of this file
    (``[...](docs/costs.md#report)``) its figures (``summary``); a link
    whose words are the page's name only points there."""
    def words(m):
        if m[3] not in BY_KEY or m[1] in PLAIN:
            return m[0]
        return f"[{summary(doc.get(m[3]))}]({m[2]})"

    return LINK.sub(words, text)


def quoting() -> list[Path]:
    """The pages that quote costs: the README and the docs."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def measure(cost: Cost) -> dict:
    """One run of ``cost``'s command: wall-clock and CPU seconds (it and its
    children), the load average around it, its exit status."""
    with tempfile.TemporaryDirectory(prefix="diskf-costs-") as tmp:
        argv = [w.replace("{python}", sys.executable).replace("{tmp}", tmp) for w in cost.argv]
        load = os.getloadavg()[0]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        done = subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        wall = time.monotonic() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"command": shown(cost.argv), "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
            "load": round(max(load, os.getloadavg()[0]), 1), "cores": len(os.sched_getaffinity(0)),
            "exit": done.returncode, "date": time.strftime("%Y-%m-%d", time.gmtime()), "machine": hardware()}


def render(doc: dict) -> str:
    """docs/costs.md from docs/costs.json."""
    lines = ["# What the commands cost", "",
             "Generated by `python benchmarks/costs.py` from [costs.json](costs.json): each command run once, "
             "wall-clock time and the CPU time of it and every process it started. The README and the other "
             "pages link here instead of stating a cost. Load is the one-minute load average while it ran: "
             "above the number of cores, other work shared them and the wall-clock time is longer than on an "
             "idle machine (the CPU time much less so).", "",
             "| | what | command | wall-clock | CPU | CPU / wall-clock | load (cores) | measured |",
             "|---|---|---|---|---|---|---|---|"]
    machines = []
    for cost in COSTS:
        row = doc.get(cost.key)
        if row is None:
            lines.append(f"| <a id=\"{cost.key}\"></a>{cost.key} | {cost.what} | `{shown(cost.argv)}` | "
                         f"not measured | | | | |")
            continue
        if row["machine"] not in machines:
            machines.append(row["machine"])
        under = " (under load)" if row["load"] is None or row["load"] > row["cores"] else ""
        failed = f"; exit {row['exit']}" if row.get("exit") else ""
        cpu = "" if row.get("cpu_s") is None else duration(row["cpu_s"])
        ratio = "" if row.get("cpu_s") is None else f"{row['cpu_s'] / max(row['wall_s'], 1e-9):.2f}"
        load = "shared" if row["load"] is None else f"{row['load']:.1f}"
        note = f" ({row['note']})" if row.get("note") else ""
        lines.append(f"| <a id=\"{cost.key}\"></a>{cost.key} | {cost.what} | `{row['command']}` | "
                     f"{duration(row['wall_s'])} | {cpu} | {ratio} | {load} ({row['cores']}){under} | "
                     f"{row['date']}, machine {machines.index(row['machine']) + 1}{failed}{note} |")
    lines += ["", *(f"Machine {i}: {m}" for i, m in enumerate(machines, 1)), ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="comma list of: " + ",".join(BY_KEY))
    ap.add_argument("--all", action="store_true", help="every entry, the long ones too (about an hour)")
    ap.add_argument("--render", action="store_true", help="only write costs.md again from costs.json")
    a = ap.parse_args(argv)
    keys = a.only.split(",") if a.only else [c.key for c in COSTS if a.all or c.default]
    unknown = sorted(set(keys) - set(BY_KEY))
    if unknown:
        ap.error(f"unknown entries {', '.join(unknown)}; choose from {', '.join(BY_KEY)}")
    doc = json.loads(JSON.read_text()) if JSON.exists() else {}
    write(doc)
    for key in [] if a.render else keys:
        print(f"costs: {key}: {shown(BY_KEY[key].argv)}", file=sys.stderr, flush=True)
        doc[key] = measure(BY_KEY[key])
        print(f"costs: {key}: {summary(doc[key])}, load {doc[key]['load']}", file=sys.stderr, flush=True)
        write(doc)
    return 0


def write(doc: dict) -> None:
    """costs.json, costs.md and every page's links, together: each entry as
    soon as it is measured, so the pages agree with the file whenever a
    measured command (the tests among them) reads them."""
    JSON.write_text(json.dumps(doc, indent=1) + "\n")
    MARKDOWN.write_text(render(doc))
    for page in quoting():
        text = page.read_text()
        if relink(text, doc) != text:
            page.write_text(relink(text, doc))


if __name__ == "__main__":
    sys.exit(main())
