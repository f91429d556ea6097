"""One edge, more robots: longest event-loop stall, peer timeouts and duplicates (#20 item 0).

For each robot count (default 3, 6, 9) the synthetic dataset of that many robots (30 s,
seed 23, built once under ``--data-root``) runs through the whole job as ``recslam demo
--no-dashboard --rate realtime`` runs it (cloud, one edge, the robots as processes on
loopback), and :func:`lab.edge_load.read_run` reads the edge's stall record, every
``PeerTimeoutError`` in the logs, each robot link's reconnects, duplicates, resends and late
acks, and the ATE. Nothing is faulted: every timeout and duplicate is the system's own doing.

Run: ``.venv/bin/python benchmarks/bench_edge_robots.py [--robots 3,6,9] [--seconds 30]
[--data-root /work/runs/edge-load/data] [--out /work/runs/edge-load]``; writes
``benchmarks/results/edge_robots.md`` and ``.png``.
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import threading
import time
from pathlib import Path

from common.links import WireFormat
from lab.edge_load import read_run, write_table
from lab.links import git_commit, run_job
from lab.seeds import ensure_dataset

log = logging.getLogger("bench_edge_robots")
RESULTS = Path(__file__).resolve().parent / "results" / "edge_robots.md"


class LoadSampler:
    """The 1-min load average every 10 s while a run goes (other jobs share the machine)."""

    def __init__(self) -> None:
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(10.0):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> LoadSampler:
        self.samples.append(os.getloadavg()[0])
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="3,6,9", help="robot counts, comma-separated")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--data-root", type=Path, default=Path("/work/runs/edge-load/data"))
    ap.add_argument("--out", type=Path, default=Path("/work/runs/edge-load"))
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--timeout", type=float, default=1800.0, help="per run (s)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    counts = [int(x) for x in args.robots.split(",") if x.strip()]
    commit = git_commit()
    runs = []
    for n in counts:
        data = args.data_root / f"robots{n}-seed{args.seed}"
        if ensure_dataset(data, n, args.seconds, args.seed):
            log.info("built %s", data)
        t0 = time.monotonic()
        with LoadSampler() as load:
            run_job(
                data, args.out / f"robots{n}", WireFormat.CODED, "realtime", args.timeout, f"[{n}]"
            )
        r = read_run(args.out / f"robots{n}")
        r["load"] = (sum(load.samples) / len(load.samples), max(load.samples))
        log.info(
            "%d robots in %.0f s: stall max %s s, timeouts %s, duplicates %d, joint %s",
            n,
            time.monotonic() - t0,
            r["stall_max_s"],
            r["timeouts"],
            r["duplicates"],
            r["joint_m"],
        )
        runs.append(r)
    loads = ", ".join(f"{r['robots']}: {r['load'][0]:.1f} / {r['load'][1]:.1f}" for r in runs)
    header = (
        "# One edge, 3 / 6 / 9 robots: event-loop stalls, timeouts, duplicates\n\n"
        f"`benchmarks/bench_edge_robots.py --robots {args.robots} --seconds {args.seconds:g} "
        f"--seed {args.seed}` at {commit}, {datetime.date.today()}: the synthetic dataset of "
        f"each robot count ({args.seconds:g} s per robot, seed {args.seed}) through the whole "
        "job (`recslam demo --no-dashboard --rate realtime`: cloud, one edge, the robots as "
        "processes on loopback, 2 cores), no fault injected. One run per row. Load average "
        f"(1 min, sampled every 10 s) mean / max during each run: {loads}.\n\n"
        "Peer timeouts: `PeerTimeoutError` lines in all the run's logs. Reconnects: robot "
        "links' connections beyond the first. Late acks: retransmission timeouts on a live "
        "connection whose peer was talking (no resend, `common/protocol/recovery.py`)."
    )
    png = write_table(runs, args.results, header)
    log.info("wrote %s and %s", args.results, png)


if __name__ == "__main__":
    main()
