"""Real browser test: the dashboard in headless Chromium (Debian's), driven by playwright.

Starts one dashboard on the synthetic three-robot map and one on an empty map, screenshots
both, and checks that agent-coloured points are drawn (and absent from the empty scene) and
that the panels show the map's counts. The screenshot is kept in tests/artifacts/; set
RECSLAM_UPDATE_SCREENSHOT=1 to also refresh docs/dashboard.png (written when missing).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.map_view import (
    KeyframeSet,
    MapDelta,
    PointSet,
    StaticMapSource,
    StatsSnapshot,
    counts_of,
)
from dashboard.demo import DemoConfig, make_demo_map
from dashboard.scene import AGENT_COLORS
from dashboard.viewer import Dashboard, DashboardConfig, new_access_token
from lab.browser import CHROMIUM, CHROMIUM_FLAGS

REPO = Path(__file__).resolve().parents[2]
ARTIFACTS = REPO / "tests" / "artifacts"

pytestmark = [
    pytest.mark.skipif(
        not CHROMIUM.exists(),
        reason="/usr/bin/chromium absent (run scripts/install-browser.sh as root)",
    ),
    pytest.mark.timeout(120),
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def agent_pixel_counts(png: bytes, tol: int = 12) -> list[int]:
    """Pixels within ``tol`` (per channel) of each agent colour, for the first three agents."""
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    rgb = bgr[..., ::-1].astype(np.int16)
    return [
        int(np.count_nonzero(np.all(np.abs(rgb - np.array(c)) <= tol, axis=-1)))
        for c in AGENT_COLORS[:3]
    ]


def _empty_source() -> StaticMapSource:
    pts, kfs = PointSet.empty(), KeyframeSet.empty()
    stats = StatsSnapshot(0.0, (), counts_of(pts, kfs, 0, 0))
    return StaticMapSource(MapDelta(1, -1, True, pts, keyframes=kfs), stats)


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS)
        yield b
        b.close()


def _open(browser, url: str):
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(url)
    page.wait_for_selector("text=Connected", timeout=30_000)
    page.wait_for_selector("text=Map points", timeout=30_000)
    close = page.locator(".mantine-Notification-closeButton")  # "software WebGL" notice
    if close.count():
        close.first.click()
    return page


def _settled_shot(page, want_points: bool, timeout_s: float = 30.0) -> bytes:
    """Screenshot once the scene has drawn (agent pixels stop changing) or the timeout."""
    t_end = time.monotonic() + timeout_s
    last = None
    while True:
        png = page.screenshot()
        counts = agent_pixel_counts(png)
        stable = last is not None and abs(sum(counts) - sum(last)) <= 0.02 * max(sum(counts), 1)
        if time.monotonic() > t_end or (stable and (min(counts) > 0 or not want_points)):
            return png
        last = counts
        time.sleep(1.0)


@pytest.mark.slow
def test_dashboard_draws_points_and_panels_in_chromium(browser, tmp_path):
    delta, stats = make_demo_map(DemoConfig(n_points=30_000))
    stats = dataclasses.replace(stats, status="overloaded for 12 s: no full BA while running")
    token = new_access_token()  # the demo view goes through the token and cookie, as users do
    demo = Dashboard(
        StaticMapSource(delta, stats), DashboardConfig("127.0.0.1", _free_port(), token)
    )
    empty = Dashboard(_empty_source(), DashboardConfig("127.0.0.1", _free_port()))
    with demo, empty:
        page = _open(browser, demo.url)
        png = _settled_shot(page, want_points=True)
        text = page.inner_text("body")
        page.get_by_text("Map with MBP").click()  # hide what map backbone profiling pruned
        mbp_png = _settled_shot(page, want_points=True, timeout_s=10.0)
        mbp_state = demo.mbp_checkbox.value
        empty_page = _open(browser, empty.url)
        empty_png = _settled_shot(empty_page, want_points=False, timeout_s=5.0)
        empty_text = empty_page.inner_text("body")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "dashboard.png").write_bytes(png)
    (ARTIFACTS / "dashboard_empty.png").write_bytes(empty_png)
    (ARTIFACTS / "dashboard_mbp.png").write_bytes(mbp_png)
    docs = REPO / "docs" / "dashboard.png"
    if not docs.exists() or os.environ.get("RECSLAM_UPDATE_SCREENSHOT") == "1":
        docs.parent.mkdir(exist_ok=True)
        shutil.copyfile(ARTIFACTS / "dashboard.png", docs)

    drawn = agent_pixel_counts(png)
    blank = agent_pixel_counts(empty_png)
    assert all(n > 2000 for n in drawn), f"agent-coloured pixels {drawn} (map not drawn?)"
    assert all(n < 50 for n in blank), f"empty scene has agent-coloured pixels {blank}"
    with_mbp = agent_pixel_counts(mbp_png)
    assert mbp_state, "clicking the MBP checkbox did not reach the server"
    assert sum(with_mbp) < 0.97 * sum(drawn), f"MBP view {with_mbp} vs full map {drawn}"
    # Panels: counts and agents as the source reports them.
    c = stats.counts
    assert "Map points" in text and str(c.map_points) in text and str(c.map_points_kept) in text
    assert str(c.keyframes) in text and str(c.keyframes_kept) in text
    for a in range(3):
        assert f"robot{a}\t" in text  # agents by their robot names (a table cell)
    assert "tracking" in text and "merged" in text
    # Edges (two sites in the demo): which robot is on which edge, each edge's link rates.
    assert "site-a→cloud" in text and "site-b→cloud" in text and "robot0→site-a" in text
    assert "robot0\tsite-a" in text and "robot2\tsite-b" in text
    assert "robots→edge" in text and "robot0, robot1" in text and "robot2" in text
    assert "no edges yet" in empty_text
    assert "no agents yet" in empty_text and str(c.map_points) not in empty_text
    # The source's own state (the cloud shedding work under load), only where there is one.
    assert "Cloud: overloaded for 12 s: no full BA while running" in text
    assert "Cloud:" not in empty_text
