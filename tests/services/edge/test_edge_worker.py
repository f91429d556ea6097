"""Worker processes: single-threaded BLAS unless the operator chose otherwise."""

from __future__ import annotations

import asyncio
from pathlib import Path

from common.data.euroc import find_mav0, read_camera_yaml, read_imu_yaml
from services.edge.worker import SINGLE_THREAD_ENV, ProcessWorker, WorkerSpec


def _child_env(excerpt: Path) -> dict[str, str]:
    mav0 = find_mav0(excerpt)
    spec = WorkerSpec(
        "r0",
        read_camera_yaml(mav0 / "cam0" / "sensor.yaml"),
        read_imu_yaml(mav0 / "imu0" / "sensor.yaml"),
    )
    worker = ProcessWorker(spec)

    async def run() -> dict[str, str]:
        await worker.start()
        try:
            assert worker.pid is not None
            raw = Path(f"/proc/{worker.pid}/environ").read_bytes()
        finally:
            await worker.close()
        return dict(item.split("=", 1) for item in raw.decode().split("\0") if "=" in item)

    return asyncio.run(run())


def test_worker_process_runs_single_threaded_blas(monkeypatch, euroc_micro: Path) -> None:
    for name in SINGLE_THREAD_ENV:
        monkeypatch.delenv(name, raising=False)
    env = _child_env(euroc_micro)
    assert {k: env.get(k) for k in SINGLE_THREAD_ENV} == SINGLE_THREAD_ENV


def test_operator_blas_threads_are_kept(monkeypatch, euroc_micro: Path) -> None:
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    env = _child_env(euroc_micro)
    assert env["OPENBLAS_NUM_THREADS"] == "2"
