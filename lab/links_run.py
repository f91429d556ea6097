"""``recslam experiment links`` end to end: run (or find) every run, read them
(:mod:`lab.links`) and write the tables (:mod:`lab.links_report`). Kept apart from both so
that the report reads the measurements and this module drives the two, one way."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from common.errors import RecslamError
from lab.links import (
    LinksConfig,
    LinksError,
    build_data,
    dataset_names,
    find_runs,
    run_folder,
    run_one,
)
from lab.links_report import write_links

log = logging.getLogger(__name__)


def run_links(config: LinksConfig) -> tuple[dict[str, Any], list[Path]]:
    """Run (or, with ``from_runs``, find) every run, then write the tables; returns the data
    and the files written."""

    errors: list[str] = []
    if config.from_runs:
        folders = find_runs(config.out, config.wires)
        if not folders:
            raise LinksError(f"--from-runs: no finished run under {config.out}/*/<wire>/run*/")
        paths = None
    else:
        if config.runs < 1:
            raise LinksError("--runs must be at least 1")
        paths = dataset_names(config.datasets)
        for path in paths.values():
            if not path.is_dir():
                raise LinksError(f"--data {path}: no such dataset folder (recslam dataset synth)")
        folders = {name: {w.value: [] for w in config.wires} for name in paths}
        todo = [(n, k, w) for n in paths for k in range(1, config.runs + 1) for w in config.wires]
        t_all = time.perf_counter()
        for i, (name, k, wire) in enumerate(todo, 1):
            label = f"[{i}/{len(todo)} {name} {wire.value} run{k}]"
            report_dir = run_folder(config.out, name, wire, k)
            log.info("%s starting (a run takes ~5 min here)", label)
            t = time.perf_counter()
            try:
                report = run_one(paths[name], report_dir, wire, config, label)
            except RecslamError as exc:
                log.error("%s failed: %s", label, exc)
                errors.append(f"{name} {wire.value} run{k}: {exc}")
                continue
            folders[name][wire.value].append(report_dir)
            log.info(
                "%s done in %.0f s: joint ATE %s m, failed services %s",
                label,
                time.perf_counter() - t,
                report["ate"]["joint_rmse_m"],
                report["failed"] or "none",
            )
        log.info("all %d runs done in %.0f s", len(todo), time.perf_counter() - t_all)
    data = build_data(folders, config, paths, errors)
    files = write_links(data, config.out, config.results)
    return data, files
