"""The cloud service on real loopback TCP: two edges' robots merge, corrections flow back,
trajectories are written, a restart resumes without duplicates, a bad edge is isolated."""

from __future__ import annotations

import asyncio
import json
import re
import socket

import numpy as np
import pytest

from common.evaluation.trajectory import Trajectory
from common.evaluation.tum import read_tum, write_tum
from common.geometry import R_to_quat_wxyz, inverse_T, transform_points
from common.links.edge_cloud import (
    MapPlacement,
    PoseCorrection,
    PoseCorrectionCoded,
    decode_map_placement,
    decode_pose_correction,
)
from common.protocol import SessionConfig
from common.protocol.arrays import pack_array
from common.transport import Client, Delivery, TransportConfig, run
from common.vocabulary import Vocabulary
from services.cloud.core_actions import SolveKind
from services.cloud.fusion.merge import yaw_of
from services.cloud.server import CloudServer
from services.cloud.service_config import (
    CloudServiceConfig,
    FullBAScheduleConfig,
    MapViewConfig,
    OptimizationScheduleConfig,
    ProcessConfig,
    StoreConfig,
)
from services.cloud.store.map_source import CloudMapSource
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_session,
    make_session,
    make_world,
    yaw_T,
)

SECRET = b"cloud-service-test-secret"
FAST = TransportConfig(reconnect_initial_delay=0.01, reconnect_max_delay=0.2)
T_A1_WORLD = yaw_T(np.radians(-60.0), np.array([-1.5, 0.5, 0.0]))


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def scenario(vocab):
    """Two robots in one room (robot r1's map offset by a known yaw + translation), coded as
    an edge sends them: per robot a list of messages (keyframe, then its new map points)."""
    world = make_world(51)
    cam = default_camera()
    poses0 = circle_poses(24, turns=1.0)
    poses1 = circle_poses(12, turns=0.5, phase=2.0)
    sessions = {
        "r0": (make_session(world, cam, 0, poses0, np.eye(4), seed=1), poses0, np.eye(4)),
        "r1": (
            make_session(world, cam, 1, poses1, T_A1_WORLD, seed=2, t0=50.0),
            poses1,
            T_A1_WORLD,
        ),
    }
    out = {}
    for name, ((kfs, mps), poses, T_agent_world) in sessions.items():
        msgs = [m for group in encode_session(kfs, mps, name, vocab, 7) for m in group]
        out[name] = {
            "messages": msgs,
            "truth": poses,
            "T_agent_world": T_agent_world,
            "n_keyframes": len(kfs),
        }
    return out


class Edge:
    """An edge-like client: sends messages, collects PoseCorrections."""

    def __init__(self, name: str, port: int, **session_kw) -> None:
        self.corrections: list[PoseCorrection | PoseCorrectionCoded] = []
        self.placements: list[MapPlacement] = []
        self.client = Client(
            SessionConfig("edge", name, SECRET, **session_kw),
            self._on,
            "127.0.0.1",
            port,
            transport=FAST,
            stop_on_reject=False,  # as the edge's uplink: a refused message is skipped
        )

    async def _on(self, d: Delivery) -> None:
        if isinstance(d.message, MapPlacement):
            self.placements.append(d.message)
            return
        assert isinstance(d.message, PoseCorrectionCoded)  # the coded wire is the default
        self.corrections.append(d.message)

    async def start(self) -> Edge:
        await self.client.start()
        return self

    async def send_all(self, messages) -> None:
        for m in messages:
            await self.client.send(m)


async def _until(predicate, timeout: float = 180.0) -> None:
    async def loop() -> None:
        while not await predicate():
            await asyncio.sleep(0.05)

    await asyncio.wait_for(loop(), timeout)


def _cloud(
    tmp_path, vocab, decode_workers: int = 0, full_ba_quiet_s: float = 0.0, **kw
) -> CloudServer:
    cfg = CloudServiceConfig(
        schedule=OptimizationScheduleConfig(debounce_s=0.2),
        full_ba=FullBAScheduleConfig(quiet_s=full_ba_quiet_s),
        map_view=MapViewConfig(publish_every_s=0.2, gt_every_s=0),
        store=StoreConfig(output_every_s=0),
        processes=ProcessConfig(decode_workers=decode_workers),
    )
    session = SessionConfig("cloud", "cloud", SECRET, **kw.pop("session", {}))
    return CloudServer(
        session,
        tmp_path / "state",
        default_camera(),
        vocab,
        cfg,
        results_dir=tmp_path / "results",
        transport=FAST,
        **kw,
    )


@pytest.mark.slow
def test_two_edges_merge_send_corrections_and_write_trajectories(tmp_path, vocab, scenario):
    T_map_world = np.eye(4)

    gt = tmp_path / "gt"
    gt.mkdir()
    for name, t0 in (("r0", 0.0), ("r1", 50.0)):
        T = scenario[name]["truth"]
        ts = np.round((t0 + 0.5 * np.arange(T.shape[0])) * 1e9).astype(np.int64)
        q = np.array([R_to_quat_wxyz(t[:3, :3]) for t in T])
        write_tum(gt / f"{name}.tum", Trajectory(ts, T[:, :3, 3], q, name))

    async def main():
        cloud = _cloud(tmp_path, vocab, groundtruth=gt)
        _, port = await cloud.start()
        a, b = await Edge("edge-a", port).start(), await Edge("edge-b", port).start()
        try:
            await asyncio.gather(
                a.send_all(scenario["r0"]["messages"]), b.send_all(scenario["r1"]["messages"])
            )
            await asyncio.gather(a.client.flush(), b.client.flush())
            stats = await cloud.stats()
            assert stats.keyframes == 36 and stats.merges == 1 and len(stats.maps) == 1
            assert stats.rejected == 0
            # Per-stage timings: each new keyframe was queried, inserted and committed once;
            # at most one message per edge link waited for the worker.
            st = stats.stages
            for stage in ("stage.place_recognition", "stage.database", "handle.KeyframeUpdate"):
                assert st[stage]["messages"] == 36, stage
            assert st["wait.worker"]["messages"] == stats.messages
            assert 1 <= stats.worker_queue_max <= 2 and stats.worker_queue == 0
            # Either map may absorb the other; the merged map has that robot's frame.
            T_map_world[:] = np.eye(4) if stats.maps == (0,) else T_A1_WORLD

            # The merge scheduled an optimisation; both edges get their robots' poses back.
            async def both_corrected() -> bool:
                return bool(a.corrections) and bool(b.corrections)

            await _until(both_corrected)
            stages = (await cloud.stats()).stages
            assert stages["solve.pose_graph"]["messages"] >= 1
            assert stages["stage.pose_graph_apply"]["messages"] >= 1
            merge = await cloud.call(lambda app: app.atlas.merges()[0])
            T_exp = inverse_T(T_A1_WORLD) if merge.target_map == 0 else T_A1_WORLD
            assert np.linalg.norm(merge.T_target_source[:3, 3] - T_exp[:3, 3]) < 0.02
            yaw_err = yaw_of(merge.T_target_source[:3, :3]) - yaw_of(T_exp[:3, :3])
            assert abs(np.degrees(yaw_err)) < 0.2
            for edge, name in ((a, "r0"), (b, "r1")):
                c = edge.corrections[-1]
                assert c.agent_id == name and c.map_id == 7
                ids, T = decode_pose_correction(c)
                sc = scenario[name]
                # In the robot's OWN map frame: its truth expressed in that frame.
                p_true = transform_points(sc["T_agent_world"], sc["truth"][ids, :3, 3])
                assert np.max(np.linalg.norm(T[:, :3, 3] - p_true, axis=1)) < 0.05
            # Each robot's map placed in the merged map: both give one world frame.
            T_global_world = []
            for edge, name in ((a, "r0"), (b, "r1")):
                place = edge.placements[-1]
                assert place.agent_id == name and place.map_id == 7
                T_global_map = decode_map_placement(place)
                T_global_world.append(T_global_map @ scenario[name]["T_agent_world"])
            assert a.placements[-1].global_map == b.placements[-1].global_map
            assert np.linalg.norm(T_global_world[0][:3, 3] - T_global_world[1][:3, 3]) < 0.05
            yaw_gap = yaw_of(T_global_world[0][:3, :3]) - yaw_of(T_global_world[1][:3, :3])
            assert abs(np.degrees(yaw_gap)) < 0.5

            # Dashboard view: a full snapshot, then an empty incremental one.
            v = await cloud.publish()
            full = cloud.map_source.snapshot(-1)
            assert full.full and len(full.keyframes) == 36 and len(full.merges) == 1
            assert not full.keyframes.T_world_body.flags.writeable
            assert set(full.current_pose) == {0, 1}
            # Ground truth aligned to the merged map: it lies on the keyframes.
            assert sorted(g.agent_id for g in full.ground_truth) == [0, 1]
            for g in full.ground_truth:
                mine = full.keyframes.agent == g.agent_id
                t_kf = full.keyframes.timestamp[mine]
                idx = np.searchsorted(g.timestamp, t_kf - 1e-6)
                p_kf = full.keyframes.T_world_body[mine][:, :3, 3]
                assert np.max(np.linalg.norm(g.p_world[idx] - p_kf, axis=1)) < 0.05
            assert cloud.map_source.snapshot(v).empty
            st = cloud.map_source.stats()
            assert {r.status.value for r in st.agents} == {"merged"}
            assert {(r.name, r.edge) for r in st.agents} == {("r0", "edge-a"), ("r1", "edge-b")}
            assert any(s.link == "edge-a→cloud" for s in st.bandwidth)
        finally:
            await a.client.close()
            await b.client.close()
            await cloud.stop()
        # Trajectories of both robots in the merged map's frame (= r0's = the world).
        for name in ("r0", "r1"):
            traj = read_tum(tmp_path / "results" / "trajectories" / f"{name}.tum")
            assert len(traj.timestamps_ns) == scenario[name]["n_keyframes"]
            p_true = transform_points(T_map_world, scenario[name]["truth"][:, :3, 3])
            err = np.linalg.norm(traj.p_world_body - p_true, axis=1)
            assert err.max() < 0.05
        maps = json.loads((tmp_path / "results" / "cloud_maps.json").read_text())
        assert maps["joint_frame"] is True
        report = json.loads((tmp_path / "results" / "eval" / "ate.json").read_text())
        assert report["joint"]["stats_m"]["rmse"] < 0.05

    run(main())


@pytest.mark.slow
def test_a_stop_waits_for_the_full_ba_in_flight_and_applies_it(tmp_path, vocab, scenario):
    """After a burst that overloaded the worker, the load is measured again without messages,
    so the quiet full BA runs; a stop that arrives while it is in the optimizer waits for it
    and applies it (before, the stop abandoned the solve, and the shutdown's own full BA queued
    behind the abandoned one in the optimizer process)."""

    async def main():
        cloud = _cloud(tmp_path, vocab, full_ba_quiet_s=0.05)
        _, port = await cloud.start()
        a = await Edge("edge-a", port).start()
        try:
            await a.send_all(scenario["r0"]["messages"])
            await a.client.flush()

            core = cloud._core
            assert core is not None

            def unchanged_since_the_full_ba_in_flight() -> bool:
                # (a full BA begun mid-burst, under CI load, saw later keyframes: the shutdown
                # then owes one more; wait for the one that saw everything)
                s = cloud.solving
                return (
                    s is not None
                    and s[0] is SolveKind.FULL_BA
                    and all(core.changed_since_full_ba(m) == 0 for m in core.app.atlas.maps())
                )

            async def full_ba_in_flight() -> int:
                while not unchanged_since_the_full_ba_in_flight():
                    await asyncio.sleep(0.002)
                return core.full_bas

            applied_before = await asyncio.wait_for(full_ba_in_flight(), 120.0)
        finally:
            await a.client.close()
            await cloud.stop(write_output=False)
        stats = await cloud.stats()
        assert stats.solves_abandoned == 0
        # The one in flight, applied; the shutdown's is not needed: nothing changed since.
        assert stats.full_ba_passes == applied_before + 1
        assert stats.overload["overloaded"] == 0

    run(main())


@pytest.mark.slow
def test_restart_resumes_acknowledged_keyframes_without_duplicates(tmp_path, vocab, scenario):
    msgs = scenario["r0"]["messages"]
    half = len(msgs) // 2

    async def main():
        # The first cloud never acknowledges (huge ack delay, no heartbeats): when it stops,
        # the edge still holds every message as unacknowledged and replays them all.
        slow_acks = {
            "ack_delay": 1000.0,
            "ack_every": 100000,
            "heartbeat_interval": 100.0,
            "idle_timeout": 200.0,
        }
        cloud = _cloud(tmp_path, vocab, session=slow_acks)
        _, port = await cloud.start()
        edge = await Edge("edge-a", port).start()
        try:
            await edge.send_all(msgs[:half])

            async def all_in() -> bool:
                return (await cloud.stats()).messages == half

            await _until(all_in)
            n_before = (await cloud.stats()).keyframes
            keys_before = await cloud.call(lambda app: app.atlas.keyframe_keys())
            assert edge.client.peer.link.first_unacked == 1  # nothing acknowledged yet
            await cloud.stop(write_output=False)

            cloud2 = _cloud(tmp_path, vocab)
            await cloud2.start("127.0.0.1", port)
            try:
                # Every keyframe is back: kept, or retired by the MBP pass at shutdown.
                kept = await cloud2.call(lambda app: app.atlas.keyframe_keys())
                retired = await cloud2.call(lambda app: [r.key for r in app.atlas.state().retired])
                assert sorted([*kept, *retired]) == keys_before
                await edge.send_all(msgs[half:])
                await edge.client.flush()
                stats = await cloud2.stats()
                # Only the messages after the durable position reached the new cloud.
                assert stats.messages == len(msgs) - half
                n_all = stats.keyframes + len(retired)
                assert n_all == scenario["r0"]["n_keyframes"] > n_before
            finally:
                await cloud2.stop(write_output=False)
        finally:
            await edge.client.close()

    run(main())


@pytest.mark.slow
def test_malformed_message_is_refused_once_and_disturbs_no_edge(tmp_path, vocab, scenario):
    good_msgs = scenario["r1"]["messages"]

    async def main():
        cloud = _cloud(tmp_path, vocab)
        _, port = await cloud.start()
        good, bad = await Edge("edge-good", port).start(), await Edge("edge-bad", port).start()
        try:
            # Garbage bytes on a raw socket: the cloud closes that connection (EOF or reset).
            assert await asyncio.to_thread(_garbage_connection, port) == "closed"
            # A well-framed KeyframeUpdate whose pose has 3 numbers instead of 16.
            bad_msg = scenario["r0"]["messages"][0]
            broken = type(bad_msg)(
                **{
                    **{f: getattr(bad_msg, f) for f in bad_msg.__slots__},
                    "T_world_body": pack_array(np.zeros(3), "<f8"),
                }
            )
            await bad.client.send(broken)
            await good.send_all(good_msgs)
            await good.client.flush()
            await bad.client.flush()  # refused once, with the reason: the stream moves on
            stats = await cloud.stats()
            assert stats.rejected == 1  # handled once, never redelivered
            assert [seq for seq, _ in bad.client.peer.rejections] == [1]
            assert "T_world_body" in bad.client.peer.rejections[0][1]
            assert bad.client.connections == 1 and good.client.connections == 1
            assert stats.keyframes == scenario["r1"]["n_keyframes"]
        finally:
            await good.client.close()
            await bad.client.close()
            await cloud.stop(write_output=False)

    run(main())


@pytest.mark.slow
def test_keyframes_decoded_in_the_decode_process_land_as_decoded_on_the_worker(
    tmp_path, vocab, scenario
):
    """With a decode process, each keyframe's features are decoded there and the worker takes
    them (none decoded twice); a payload that does not decode is still refused once, by the
    worker, with the codec's reason, and the atlas holds exactly the good keyframes."""
    msgs = scenario["r1"]["messages"]
    first = next(m for m in msgs if getattr(m, "features", b""))
    broken = type(first)(
        **{
            **{f: getattr(first, f) for f in first.__slots__},
            "keyframe_id": 999,
            "features": first.features[:-9] + bytes(9),  # CRC and body broken
        }
    )

    async def main():
        cloud = _cloud(tmp_path, vocab, decode_workers=1)
        _, port = await cloud.start()
        edge = await Edge("edge-a", port).start()
        try:
            await edge.send_all([*msgs, broken])
            await edge.client.flush()
            stats = await cloud.stats()
            assert stats.keyframes == scenario["r1"]["n_keyframes"]
            assert stats.rejected == 1 and "features" in edge.client.peer.rejections[0][1]
            taken = await cloud.call(lambda app: app.decoders.taken)
            assert taken == sum(1 for m in msgs if getattr(m, "features", b""))
            descs = await cloud.call(
                lambda app: [app.atlas.keyframe(k).descriptors for k in app.atlas.keyframe_keys()]
            )
        finally:
            await edge.client.close()
            await cloud.stop(write_output=False)
        # the same keyframes as the worker decodes them itself
        (tmp_path / "inline").mkdir()

        async def inline():
            cloud = _cloud(tmp_path / "inline", vocab)
            _, port = await cloud.start()
            edge = await Edge("edge-a", port).start()
            try:
                await edge.send_all(msgs)
                await edge.client.flush()
                assert await cloud.call(lambda app: app.decoders.taken) == 0
                return await cloud.call(
                    lambda app: [
                        app.atlas.keyframe(k).descriptors for k in app.atlas.keyframe_keys()
                    ]
                )
            finally:
                await edge.client.close()
                await cloud.stop(write_output=False)

        ref = await inline()
        assert len(ref) == len(descs)
        assert all(np.array_equal(a, b) for a, b in zip(ref, descs, strict=True))

    run(main())


def _garbage_connection(port: int) -> str:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"\x00garbage" * 64)
        try:
            while s.recv(1 << 16):
                pass
        except ConnectionResetError:
            pass
        except TimeoutError:
            return "still open"
    return "closed"


def test_map_source_versions_and_pruned_items():
    from common.map_view import MapSource
    from services.cloud.atlas.atlas import Atlas
    from services.cloud.store.map_source import CloudView
    from sim.cloud import default_camera as cam

    world = make_world(3, n_points=800)
    kfs, mps = make_session(world, cam(), 0, circle_poses(6, turns=0.3), np.eye(4), seed=4)
    atlas = Atlas()
    for m in mps:
        atlas.add_map_point(m)
    for k in kfs:
        atlas.add_keyframe(k)
    src = CloudMapSource()
    assert isinstance(src, MapSource)
    v1 = src.publish(CloudView(atlas.snapshot(), (), frozenset(), frozenset()))
    d1 = src.snapshot(-1)
    assert d1.full and len(d1.keyframes) == 6 and d1.version == v1
    # Nothing changed: same version, empty delta.
    assert src.publish(CloudView(atlas.snapshot(), (), frozenset(), frozenset())) == v1
    # Move one keyframe, prune another: only those two are in the delta.
    keys = atlas.keyframe_keys()
    atlas.set_keyframe_poses({keys[1]: atlas.T_map_body(keys[1]) @ yaw_T(0.1, np.zeros(3))})
    atlas.remove_keyframe(keys[4])
    v2 = src.publish(CloudView(atlas.snapshot(), (), frozenset({keys[4]}), frozenset()))
    d2 = src.snapshot(v1)
    assert not d2.full and v2 == v1 + 1
    assert sorted(d2.keyframes.ids.tolist()) == [keys[1], keys[4]]
    assert d2.keyframes.pruned.tolist() == [False, True]
    assert d2.removed_keyframe_ids.size == 0
    # An edge cull (not MBP) removes it for good.
    atlas.remove_keyframe(keys[2])
    v3 = src.publish(CloudView(atlas.snapshot(), (), frozenset({keys[4]}), frozenset()))
    assert src.snapshot(v2).removed_keyframe_ids.tolist() == [keys[2]]
    assert len(src.snapshot(-1).keyframes) == 5 and src.snapshot(-1).version == v3
    # The service's state in words reaches the panels' stats.
    assert src.stats().status == ""
    view = CloudView(atlas.snapshot(), (), frozenset({keys[4]}), frozenset(), status="busy")
    src.publish(view)
    assert src.stats().status == "busy"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_cloud_command_survives_sigkill_then_stops_on_sigterm_and_writes_results(
    tmp_path, vocab, scenario
):
    """``recslam cloud`` as a real process: killed (SIGKILL) while an edge streams to it, a new
    process on the same state directory resumes: every keyframe arrives exactly once; SIGTERM
    stops it cleanly with the trajectories and the ATE report in the result folder."""
    import os
    import signal
    import subprocess
    import sys

    truth = scenario["r0"]["truth"]
    n = scenario["r0"]["n_keyframes"]
    ts = np.round(np.arange(n) * 0.5 * 1e9).astype(np.int64)
    q = np.array([R_to_quat_wxyz(T[:3, :3]) for T in truth])
    (tmp_path / "gt").mkdir()
    write_tum(tmp_path / "gt" / "r0.tum", Trajectory(ts, truth[:, :3, 3], q, "r0"))
    code = (
        "import argparse, logging, sys\n"
        "from recslam.commands import cloud\n"
        "logging.basicConfig(level=logging.INFO)\n"
        "p = argparse.ArgumentParser(); cloud.register(p.add_subparsers())\n"
        "a = p.parse_args(sys.argv[1:]); sys.exit(a.func(a))\n"
    )
    port = _free_port()
    args = [
        "cloud",
        "--listen",
        f"127.0.0.1:{port}",
        "--state-dir",
        str(tmp_path / "state"),
        "--dashboard-port",
        "0",
        "--results",
        str(tmp_path / "res"),
        "--groundtruth",
        str(tmp_path / "gt"),
        "--no-mbp",
        "--output-every",
        "0",
    ]
    env = {**os.environ, "RECSLAM_SECRET": SECRET.decode()}
    log_path = tmp_path / "cloud.log"
    procs: list[subprocess.Popen] = []

    def start() -> subprocess.Popen:
        with open(log_path, "a") as log_file:
            proc = subprocess.Popen(
                [sys.executable, "-c", code, *args],
                stdout=subprocess.PIPE,
                stderr=log_file,
                text=True,
                env=env,
            )
        procs.append(proc)
        line = proc.stdout.readline()
        assert line.startswith(f"cloud listening on 127.0.0.1:{port}"), line + log_path.read_text()
        return proc

    try:
        first = start()

        async def feed() -> None:
            edge = await Edge("edge-a", port).start()
            await edge.send_all(scenario["r0"]["messages"])

            async def some_acked() -> bool:
                return edge.client.peer.link.first_unacked > 8

            await _until(some_acked)
            first.kill()  # a crash: no clean shutdown, no final commit
            await asyncio.to_thread(first.wait)
            await asyncio.to_thread(start)
            await edge.client.flush()
            await edge.client.close()

        run(feed())
        second = procs[-1]
        second.send_signal(signal.SIGTERM)
        assert second.wait(timeout=60) == 0, log_path.read_text()
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            proc.stdout.close()
    loaded = [int(x) for x in re.findall(r"loaded (\d+) keyframes", log_path.read_text())]
    assert loaded[0] == 0 and 0 < loaded[1] <= n  # the restart resumed what was durable
    traj = read_tum(tmp_path / "res" / "trajectories" / "r0.tum")
    assert len(traj.timestamps_ns) == n
    report = json.loads((tmp_path / "res" / "eval" / "ate.json").read_text())
    assert report["joint"]["stats_m"]["rmse"] < 0.05
    assert (tmp_path / "res" / "eval" / "ate.md").is_file()


@pytest.mark.slow
def test_an_edge_cannot_cull_or_update_a_robot_another_edge_serves(tmp_path, vocab, scenario):
    """The attack of issue 18: an edge (with a valid edge credential) sends a CullEvent and a
    keyframe for a robot another edge serves. Agents are keyed by (edge, robot, edge map), so
    the cull is refused (that edge has no such agent) and the keyframe starts the intruder's
    own agent: the robot's keyframes on its edge stay, and its corrections go to its edge."""
    from common.links.edge_cloud import CullEvent

    msgs = scenario["r0"]["messages"]
    first = msgs[0]

    async def main():
        cloud = _cloud(tmp_path, vocab)
        _, port = await cloud.start()
        owner, intruder = await Edge("edge-a", port).start(), await Edge("edge-b", port).start()
        try:
            await owner.send_all(msgs)
            await owner.client.flush()
            before = (await cloud.stats()).keyframes
            ids = pack_array(np.arange(before, dtype=np.int64), "<i8")
            await intruder.client.send(CullEvent(first.agent_id, first.map_id, ids, b""))
            await intruder.client.send(first)
            await intruder.client.flush()
            assert before == scenario["r0"]["n_keyframes"]
            reasons = [r for _, r in intruder.client.peer.rejections]
            assert len(reasons) == 1 and "has no agent" in reasons[0]
            agents = await cloud.call(lambda app: app.agents())
            owned = {aid: edge for aid, (_, edge, _) in agents.items()}
            assert sorted(owned.values()) == ["edge-a", "edge-b"]
            [a_id] = [aid for aid, e in owned.items() if e == "edge-a"]
            n_a = await cloud.call(lambda app: len(app.atlas.keyframe_keys(agent_id=a_id)))
            assert n_a == before
        finally:
            await owner.client.close()
            await intruder.client.close()
            await cloud.stop(write_output=False)

    run(main())


def test_no_map_view_refresh_without_a_dashboard(tmp_path, vocab):
    """``MapViewConfig.publish_every_s`` = 0 (``recslam cloud --dashboard-port 0``): no task
    snapshots the atlas for a dashboard nobody serves."""
    cfg = CloudServiceConfig(
        map_view=MapViewConfig(publish_every_s=0.0), store=StoreConfig(output_every_s=0)
    )

    async def main():
        cloud = CloudServer(
            SessionConfig("cloud", "cloud", SECRET), tmp_path / "s", default_camera(), vocab, cfg
        )
        await cloud.start()
        try:
            names = {t.get_name() for t in cloud._tasks}
            assert "cloud-optimize" in names and "cloud-publish" not in names
        finally:
            await cloud.stop()

    run(main())
