"""The Dashboard against a real viser server (no browser) and the CLI command."""

from __future__ import annotations

import argparse
import socket

import numpy as np
import pytest

from common.map_view import MapDelta, PointSet, StaticMapSource, load_recording
from dashboard.demo import DemoConfig, make_demo_map
from dashboard.viewer import Dashboard, DashboardConfig, DashboardError
from recslam.commands import dashboard as dashboard_cmd


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _ScriptedSource:
    """A MapSource that hands out prepared deltas (the real protocol, no viser involved)."""

    def __init__(self, deltas, stats):
        self._deltas = list(deltas)
        self._stats = stats
        self.calls: list[int] = []

    def snapshot(self, since_version: int) -> MapDelta:
        self.calls.append(since_version)
        if self._deltas:
            return self._deltas.pop(0)
        return MapDelta(since_version, since_version, False)

    def stats(self):
        return self._stats


def test_config_rejects_bad_values():
    with pytest.raises(DashboardError, match="port"):
        DashboardConfig(port=0)
    with pytest.raises(DashboardError, match="update_hz"):
        DashboardConfig(update_hz=0)


def test_dashboard_builds_scene_incrementally_and_toggles_mbp():
    delta, stats = make_demo_map(DemoConfig(n_points=4000, keyframes_per_agent=20))
    moved = delta.points.subset(np.arange(5))
    moved = PointSet(moved.ids, moved.p_world + 1.0, moved.agent, moved.pruned)
    src = _ScriptedSource(
        [delta, MapDelta(2, 1, False, points=moved, loops=delta.loops, merges=delta.merges)], stats
    )
    cfg = DashboardConfig(host="127.0.0.1", port=_free_port())
    dash = Dashboard(src, cfg).start(poll=False)  # the test steps the polling itself
    try:
        dash.poll_once()
        dash.poll_once()
        assert src.calls[:2] == [-1, 1]
        assert dash.version == 2
        names = dash.scene.node_names()
        for a in range(3):
            assert f"/map/pose/a{a}" in names
            assert f"/map/traj/a{a}/all" in names
            assert f"/map/gt/a{a}" in names
        assert {"/map/links/loops", "/map/links/merges"} <= set(names)
        assert len(dash.scene.points) == 4000
        assert "| Map points | 4000 |" in dash._panels.counts.content
        assert "| robot2 | site-b |" in dash._panels.agents.content
        assert " m |" in dash._panels.agents.content
        assert dash.scene.names == {0: "robot0", 1: "robot1", 2: "robot2"}  # the labels
        handles = dash.scene._handles
        pruned = [h for n, h in handles.items() if n.startswith("/map/points") and "pruned" in n]
        assert pruned and all(h.visible for h in pruned)
        dash.scene.set_mbp(True)
        assert not any(h.visible for h in pruned)
        assert handles["/map/traj/a0/kept"].visible and not handles["/map/traj/a0/all"].visible
        dash.scene.set_mbp(False)
        assert all(h.visible for h in pruned)
    finally:
        dash.stop()


def test_cli_records_demo_and_rejects_bad_replay(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    dashboard_cmd.register(parser.add_subparsers())
    out = tmp_path / "demo.npz"
    args = parser.parse_args(["dashboard", "--demo", "--points", "1000", "--record", str(out)])
    assert args.func(args) == 0
    delta, _ = load_recording(out)
    assert len(delta.points) == 1000
    bad = tmp_path / "bad.npz"
    bad.write_text("nope")
    args = parser.parse_args(["dashboard", "--replay", str(bad), "--port", str(_free_port())])
    assert args.func(args) == 2
    assert "bad.npz" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        parser.parse_args(["dashboard"])


def test_cli_serves_replay_for_a_while(tmp_path):
    delta, stats = make_demo_map(DemoConfig(n_points=500, keyframes_per_agent=10))
    from common.map_view import save_recording

    path = tmp_path / "m.npz"
    save_recording(path, delta, stats)
    parser = argparse.ArgumentParser()
    dashboard_cmd.register(parser.add_subparsers())
    args = parser.parse_args(
        [
            "dashboard",
            "--replay",
            str(path),
            "--host",
            "127.0.0.1",
            "--port",
            str(_free_port()),
            "--seconds",
            "0.5",
        ]
    )
    assert args.func(args) == 0
    assert isinstance(StaticMapSource.from_file(path).snapshot(-1), MapDelta)


def _request(port: int, target: str, headers: dict[str, str]) -> tuple[int, dict[str, str]]:
    """One raw HTTP request to the dashboard: (status, response headers)."""
    lines = [f"GET {target} HTTP/1.1", f"Host: 127.0.0.1:{port}"]
    lines += [f"{k}: {v}" for k, v in headers.items()]
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
    head = data.split(b"\r\n\r\n")[0].decode("latin-1").split("\r\n")
    fields = dict(line.split(": ", 1) for line in head[1:] if ": " in line)
    return int(head[0].split()[1]), {k.lower(): v for k, v in fields.items()}


def test_dashboard_needs_its_token_and_a_same_origin_websocket():
    """Issue 18: without the token nothing is served (not even the page); the token URL sets
    an HttpOnly cookie; a websocket from another origin is refused even with the cookie."""
    from dashboard.viewer import new_access_token

    delta, stats = make_demo_map(DemoConfig(n_points=200, keyframes_per_agent=5))
    token = new_access_token()
    port = _free_port()
    dash = Dashboard(StaticMapSource(delta, stats), DashboardConfig("127.0.0.1", port, token))
    dash.start(poll=False)
    try:
        assert dash.url == f"http://127.0.0.1:{port}/?token={token}"
        assert _request(port, "/", {})[0] == 401
        assert _request(port, "/?token=wrong", {})[0] == 401
        status, fields = _request(port, f"/?token={token}", {})
        assert status == 302 and fields["location"] == "/"
        cookie = fields["set-cookie"].split(";")[0]
        assert "HttpOnly" in fields["set-cookie"] and "SameSite=Strict" in fields["set-cookie"]
        assert _request(port, "/", {"Cookie": cookie})[0] == 200
        upgrade = {
            "Cookie": cookie,
            "Upgrade": "websocket",
            "Connection": "Upgrade",
            "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
            "Sec-WebSocket-Version": "13",
        }
        assert _request(port, "/", {**upgrade, "Origin": "http://evil.example"})[0] == 403
        assert _request(port, "/", upgrade)[0] == 403  # no Origin at all
        ok = {**upgrade, "Origin": f"http://127.0.0.1:{port}"}
        assert _request(port, "/", ok)[0] == 101
        assert _request(port, "/", {k: v for k, v in ok.items() if k != "Cookie"})[0] == 401
    finally:
        dash.stop()


def test_dashboard_listens_on_loopback_by_default():
    assert DashboardConfig().host == "127.0.0.1"
