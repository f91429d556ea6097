"""The rate–accuracy–latency curve over kernel-shaped links (issue 47): ``lab.budget``.

Run (root, for the network namespaces):
``PYTHONPATH=. .venv/bin/python benchmarks/bench_budget.py --data DATA --rows
unlimited,unlimited/fresh,50,50/fresh --name budget`` -> ``benchmarks/results/<name>.md`` and
``<name>.png``; each run's folder under ``--work``. DATA: ``recslam dataset synth --out DATA``
(the default dataset: 3 robots × 60 s, seed 0). ``--robots robot0`` runs one robot.
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import time
from pathlib import Path

from lab.budget import parse_rows, plot, run_rows, table
from lab.links import git_commit

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--robots", default="", help="comma-separated sequence folders (default all)")
    p.add_argument("--rows", default="unlimited,unlimited/fresh,50,50/fresh,50/auto,25/fresh")
    p.add_argument("--shaper", choices=("tbf", "proxy"), default="tbf")
    p.add_argument("--work", type=Path, default=Path("/tmp/bench_budget"))
    p.add_argument("--name", default="budget")
    p.add_argument("--timeout", type=float, default=1800.0)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    robots = tuple(r for r in args.robots.split(",") if r)
    rows = parse_rows(args.rows)
    commit = git_commit()
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    results = run_rows(args.data, robots, rows, args.work, args.timeout, args.shaper, print)
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()
    png = RESULTS / f"{args.name}.png"
    plot(results, png)
    cmd = (
        f"`benchmarks/bench_budget.py --data {args.data} --robots '{args.robots}' --rows "
        f"{args.rows} --shaper {args.shaper}`"
    )
    text = (
        f"# Rate, accuracy and latency over shaped links ({args.name})\n\n"
        f"{cmd}; commit {commit}, {platform.machine()}, {os.cpu_count()} cores, "
        f"{wall:.0f} s; load average {load0[0]:.1f} at the start, {load1[0]:.1f} at the end.\n\n"
        f"![plot]({png.name})\n\n" + table(results)
    )
    (RESULTS / f"{args.name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
