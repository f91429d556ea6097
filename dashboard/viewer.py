"""The dashboard: a viser server plus one polling thread that reads a :class:`MapSource`.

viser listens on a free loopback port; the address users open is the :class:`~dashboard.gate.
Gate`'s, which checks the access token and the websocket's Origin before passing a
connection through (viser itself has no access control).

viser runs its own event loop in its own thread; our poll thread calls the source at
``update_hz`` (map deltas) and ``stats_hz`` (panels) and pushes changes through viser's
thread-safe API. Neither touches the services' asyncio loops. Poses are "latest value
wins" (one update per agent per tick, and viser drops superseded queued updates); new map
points are sent once, in per-agent chunks (see :mod:`dashboard.map_state`).
"""

from __future__ import annotations

import logging
import secrets
import socket
import threading
import time
from dataclasses import dataclass, field

import viser

from common.errors import RecslamError
from common.map_view import MapSource
from dashboard.gate import Gate
from dashboard.map_state import live_ate_rmse
from dashboard.panels import Panels
from dashboard.scene import MapScene, SceneConfig

log = logging.getLogger(__name__)


class DashboardError(RecslamError):
    """Bad dashboard configuration or misuse (e.g. starting twice)."""


@dataclass(frozen=True)
class DashboardConfig:
    """Where and how fast the dashboard serves.

    host / port: HTTP and websocket address (a fixed port: pick a free one);
    access_token: required of every browser (part of :attr:`Dashboard.url`); None serves
    anyone who can reach the address (see :func:`new_access_token`);
    update_hz: map polls per second; stats_hz: panel refreshes per second;
    bandwidth_window_s: history shown in the bandwidth plots; scene: look of the 3D scene.
    """

    host: str = "127.0.0.1"
    port: int = 8080
    access_token: str | None = field(default=None, repr=False)
    update_hz: float = 10.0
    stats_hz: float = 1.0
    bandwidth_window_s: float = 60.0
    scene: SceneConfig = field(default_factory=SceneConfig)

    def __post_init__(self) -> None:
        if not 0 < self.port < 65536:
            raise DashboardError(f"port must be in 1..65535, got {self.port}")
        if self.update_hz <= 0 or self.stats_hz <= 0:
            raise DashboardError(
                f"update_hz and stats_hz must be > 0, got {self.update_hz}, {self.stats_hz}"
            )


def new_access_token() -> str:
    """A fresh random dashboard access token (URL-safe)."""
    return secrets.token_urlsafe(18)


class Dashboard:
    """Serve the map of ``source`` at ``http://host:port``; :meth:`start` / :meth:`stop`, or
    use it as a context manager. Thread-safe counters: :attr:`version`, :attr:`ticks`."""

    def __init__(self, source: MapSource, config: DashboardConfig | None = None) -> None:
        self._source = source
        self._cfg = config or DashboardConfig()
        self._server: viser.ViserServer | None = None
        self._gate: Gate | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()  # serialises scene changes (poll thread vs GUI callbacks)
        self.version = -1
        self.ticks = 0
        self.stats_updates = 0
        self.errors = 0

    @property
    def url(self) -> str:
        host = "localhost" if self._cfg.host in ("0.0.0.0", "::") else self._cfg.host
        token = self._cfg.access_token
        return f"http://{host}:{self._cfg.port}/" + (f"?token={token}" if token else "")

    @property
    def server(self) -> viser.ViserServer:
        if self._server is None:
            raise DashboardError("dashboard is not running")
        return self._server

    def start(self, poll: bool = True) -> Dashboard:
        """Bind the server and start the poll thread (returns at once). ``poll=False`` leaves
        polling to the caller (:meth:`poll_once`), e.g. to step a test deterministically."""
        if self._server is not None:
            raise DashboardError("dashboard already started")
        inner = _free_loopback_port()
        server = viser.ViserServer(host="127.0.0.1", port=inner, verbose=False)
        gate = Gate(self._cfg.host, self._cfg.port, server.get_port(), self._cfg.access_token)
        try:
            gate.start()
        except OSError as exc:
            server.stop()
            where = f"{self._cfg.host}:{self._cfg.port}"
            raise DashboardError(f"cannot listen on {where}: {exc}") from None
        self._server, self._gate = server, gate
        server.gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        server.initial_camera.position = (2.0, -10.0, 8.0)
        server.initial_camera.look_at = (2.0, 0.0, 0.0)
        server.initial_camera.up = (0.0, 0.0, 1.0)
        self._scene = MapScene(server, self._cfg.scene)
        self._add_toggles(server)
        self._panels = Panels(server, self._cfg.bandwidth_window_s)
        if poll:
            self._thread = threading.Thread(target=self._run, name="dashboard-poll", daemon=True)
            self._thread.start()
        log.info("dashboard at %s", self.url)
        return self

    def _add_toggles(self, server: viser.ViserServer) -> None:
        with server.gui.add_folder("View"):
            mbp = server.gui.add_checkbox("Map with MBP (hide pruned)", initial_value=False)
            frustums = server.gui.add_checkbox("Keyframe frustums", initial_value=True)
            links = server.gui.add_checkbox("Loop / merge links", initial_value=True)
            gt = server.gui.add_checkbox("Ground truth", initial_value=True)

        @mbp.on_update
        def _(_: object) -> None:
            with self._lock:
                self._scene.set_mbp(mbp.value)

        @frustums.on_update
        def _(_: object) -> None:
            with self._lock:
                self._scene.show_frustums = frustums.value
                self._scene.set_layer("/map/frustums", frustums.value)

        @links.on_update
        def _(_: object) -> None:
            with self._lock:
                self._scene.show_links = links.value
                self._scene.set_layer("/map/links", links.value)

        @gt.on_update
        def _(_: object) -> None:
            with self._lock:
                self._scene.show_ground_truth = gt.value
                self._scene.set_layer("/map/gt", gt.value)

        self.mbp_checkbox = mbp

    def _run(self) -> None:
        period = 1.0 / self._cfg.update_hz
        stats_period = 1.0 / self._cfg.stats_hz
        next_stats = 0.0
        while not self._stop.is_set():
            t = time.monotonic()
            try:
                self.poll_once(with_stats=t >= next_stats)
            except Exception:  # the source is someone else's code: keep serving
                self.errors += 1
                log.exception("dashboard poll failed (%d so far)", self.errors)
            if t >= next_stats:
                next_stats = t + stats_period
            self._stop.wait(max(period - (time.monotonic() - t), 0.0))

    def poll_once(self, with_stats: bool = True) -> None:
        """Read one delta (and optionally stats) from the source and show it."""
        delta = self._source.snapshot(self.version)
        with self._lock:
            self._scene.apply(delta, time.monotonic())  # cheap when nothing changed
            self.version = delta.version
            self.ticks += 1
        if with_stats:
            stats = self._source.stats()
            with self._lock:
                self._scene.set_names({a.agent_id: a.name for a in stats.agents if a.name})
            self._panels.update(stats, self._live_ate())
            self.stats_updates += 1

    def _live_ate(self) -> dict[int, float | None]:
        out: dict[int, float | None] = {}
        with self._lock:
            for a, gt in self._scene.ground_truth.items():
                t, T, _ = self._scene.keyframes.track(a)
                out[a] = live_ate_rmse(t, T[:, :3, 3], gt)
        return out

    @property
    def scene(self) -> MapScene:
        return self._scene

    def stop(self) -> None:
        """Stop polling and shut the server down (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._gate is not None:
            self._gate.stop()
            self._gate = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    def __enter__(self) -> Dashboard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
