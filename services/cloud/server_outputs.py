"""The cloud server's outputs: the dashboard's map view and the result files.

:class:`ServerOutputs` is a base of :class:`~services.cloud.server.CloudServer`, which sets the
attributes declared here and starts the loops. :meth:`ServerOutputs.publish` refreshes the
dashboard's :class:`~services.cloud.store.map_source.CloudMapSource` every
``MapViewConfig.publish_every_s`` (longer under load, ``CloudCore.publish_every_s``), with the
known robots' ground truth reloaded every ``MapViewConfig.gt_every_s``;
:meth:`ServerOutputs.write_output` writes the trajectories (and the ATE report when ground truth
is known) every ``StoreConfig.output_every_s``. The app is read on the server's worker thread,
files are read and written on its I/O thread.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from common.evaluation.errors import EvaluationError
from common.evaluation.results import load_groundtruth
from common.evaluation.trajectory import Trajectory
from common.transport import Server
from services.cloud.app import CloudApp
from services.cloud.core import CloudCore
from services.cloud.service_config import CloudServiceConfig
from services.cloud.store.map_source import CloudMapSource, CloudView
from services.cloud.store.output import OutputWriter

log = logging.getLogger(__name__)

T = TypeVar("T")


class ServerOutputs:
    """The map view and output files of :class:`~services.cloud.server.CloudServer`."""

    config: CloudServiceConfig
    output: OutputWriter | None
    map_source: CloudMapSource
    _app: CloudApp | None
    _core: CloudCore | None
    _server: Server
    _io: ThreadPoolExecutor
    _references: dict[str, Trajectory]  # ground truth per robot name
    _no_reference: set[str]
    _gt_published: float

    if TYPE_CHECKING:  # CloudServer's

        async def _on_worker(self, fn: Callable[..., T], *args: Any) -> T: ...

    async def publish(self) -> int:
        """Refresh the dashboard's map view now; returns its version."""
        app = self._app
        assert app is not None
        counters = self._server.counters()
        references = await self._load_references()
        core, now = self._core, asyncio.get_running_loop().time()

        def build() -> CloudView:
            view = app.view(counters, references)
            status = "" if core is None else core.status(now)
            return dataclasses.replace(view, status=status) if status else view

        return self.map_source.publish(await self._on_worker(build))

    async def _load_references(self) -> dict[str, Trajectory] | None:
        """Ground truth of the known robots, every ``gt_every_s`` (None in between)."""
        source = self.output.groundtruth if self.output is not None else None
        loop = asyncio.get_running_loop()
        if source is None or loop.time() - self._gt_published < self.config.map_view.gt_every_s:
            return None
        self._gt_published = loop.time()
        app = self._app
        assert app is not None
        agents = await self._on_worker(app.agents)
        known = {n for n, _, _ in agents.values()}
        names = known - set(self._references) - self._no_reference
        single = Path(source).is_file() or (Path(source) / "mav0").is_dir()
        if single and len(known) > 1:  # one sequence's ground truth: whose is it?
            names = set()
        for name in sorted(names):
            try:
                refs, _ = await loop.run_in_executor(
                    self._io, load_groundtruth, [name], source, None
                )
            except EvaluationError as exc:
                log.info("no ground truth for %s: %s", name, exc)
                self._no_reference.add(name)
            else:
                self._references.update(refs)
        return dict(self._references) if self._references else None

    async def _publish_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            t0 = loop.time()
            try:
                await self.publish()
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("map view refresh failed")
            core = self._core  # (rests as long as the refresh took, and longer under load)
            last = loop.time() - t0
            every = (
                self.config.map_view.publish_every_s if core is None else core.publish_every_s(last)
            )
            await asyncio.sleep(every)

    async def write_output(self, evaluate: bool = True) -> list[Path]:
        """Write trajectories (and the ATE report when ground truth is known)."""
        app, out = self._app, self.output
        if app is None or out is None:
            return []
        trajs, maps = await self._on_worker(app.trajectories)
        frames = await self._on_worker(functools.partial(app.frame_trajectories, trajs))
        mission = await self._on_worker(app.mission_report)
        loop = asyncio.get_running_loop()
        write = functools.partial(out.write, frames=frames)
        return await loop.run_in_executor(self._io, write, trajs, maps, evaluate, mission)

    async def _output_loop(self) -> None:
        while True:
            await asyncio.sleep(self.config.store.output_every_s)
            try:
                await self.write_output(evaluate=True)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("writing outputs failed")
