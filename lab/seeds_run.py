"""``recslam experiment seeds`` end to end: build the datasets, run every seed (or read the
runs), summarise them (:mod:`lab.seeds`) and write the tables (:mod:`lab.seeds_report`). Kept
apart from both so that the report reads the summary and this module drives the two, one
way."""

from __future__ import annotations

import datetime
import logging
import time
from pathlib import Path
from typing import Any

from common.errors import RecslamError
from common.links import WireFormat
from lab.links import git_commit, run_job
from lab.seeds import (
    SeedsConfig,
    SeedsError,
    constraint_check,
    dataset_folder,
    dataset_of,
    ensure_dataset,
    find_runs,
    read_report,
    scale_check,
    summarize,
)
from lab.seeds_report import write_seeds

log = logging.getLogger(__name__)


def run_seeds(config: SeedsConfig) -> tuple[dict[str, Any], list[Path]]:
    """Build the datasets and run every seed (or, with ``from_runs``, read the runs under
    ``out``); write the tables. Returns the data and the files written."""
    errors: list[str] = []
    if config.from_runs:
        folders = find_runs(config.out)
        if not folders:
            raise SeedsError(f"--from-runs: no run report under {config.out}/*/report.json")
    else:
        if not config.seeds:
            raise SeedsError("no seeds to run")
        folders = {}
        t_all = time.perf_counter()
        for i, seed in enumerate(config.seeds, 1):
            label = f"[{i}/{len(config.seeds)} seed {seed}]"
            run_name = config.generator.folder(seed)
            dataset = config.data_root / run_name
            t = time.perf_counter()
            if ensure_dataset(dataset, config.robots, config.seconds, seed, config.generator):
                log.info("%s dataset built in %.0f s: %s", label, time.perf_counter() - t, dataset)
            report_dir = config.out / run_name
            log.info("%s running the whole job (a 60 s run takes ~4 min here)", label)
            try:
                report = run_job(
                    dataset, report_dir, WireFormat.CODED, config.rate, config.timeout_s, label
                )
            except RecslamError as exc:
                log.error("%s failed: %s", label, exc)
                errors.append(f"seed {seed}: {exc}")
                continue
            folders[run_name] = report_dir
            log.info(
                "%s done in %.0f s: joint ATE %s m",
                label,
                time.perf_counter() - t,
                report["ate"]["joint_rmse_m"],
            )
        log.info("%d runs done in %.0f s", len(config.seeds), time.perf_counter() - t_all)
    runs = {name: read_report(f) for name, f in folders.items()}
    for name, f in folders.items():
        played = dataset_folder(f)
        runs[name]["dataset"] = dataset_of(played)
        runs[name].update(scale_check(f, played))
        runs[name].update(constraint_check(f, played))
    data = {
        "command": config.command,
        "commit": git_commit(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "targets": config.targets.__dict__,
        "errors": errors,
        "runs": runs,
        "summary": summarize(runs, config.targets) if runs else None,
    }

    return data, write_seeds(data, config.out, config.results, config.table_name)
