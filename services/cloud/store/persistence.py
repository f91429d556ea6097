"""Durable cloud state in SQLite (stdlib ``sqlite3``, WAL journal, ``synchronous=FULL``).

The store holds keyframes and map points as the atlas has them (poses in their map's frame),
the atlas bookkeeping (agents' maps and transforms, merges, loops, fused-point aliases,
pruned keyframes, the relative poses of those MBP retired) and, per edge link, the last
delivered message sequence. A service calls
:meth:`CloudStore.commit` with what a batch of messages changed *and* the new sequence
numbers in one transaction, and acknowledges to the edge only after it returns: what was
acknowledged is on disk. :meth:`CloudStore.load` rebuilds an :class:`Atlas` from it.

Two tables serve the network service: ``edge_positions`` (the transport's inbound position
per edge link: the edge's stream id and last delivered sequence, overwritten when the edge
starts a new stream, see :meth:`CloudStore.positions`) and ``agent_names`` (each atlas agent
is one robot's map on its edge: the robot's name, the edge serving it, the edge's map id and
the mission it belongs to; unique per (mission, edge, robot, edge map), so that one robot on two
edges is two agents).

Missions (``missions``, ``meta.mission``): a state directory can hold several missions, one after
the other. The current mission's agents are live; every agent of an earlier mission belongs to
the *prior map* (read-only, see ``services.cloud.app``). :meth:`CloudStore.enter_mission` makes a
named mission current: resuming it when it already is (a crash restart runs the same command
line), else starting it, which clears the stored edge positions (the new mission's edges start
new streams). A robot name and edge map id are unique per mission and edge only, so that a new
mission's ``robot0`` on edge map 0 is a new agent, not the old one's continuation.

Rows (:mod:`services.cloud.store.persistence_schema`): keyframe arrays as ``.npz`` blobs, map point
observations as flat ``<i8`` blobs; keyframe poses and map point positions have their own
columns, and a point's position is in its reference keyframe's frame, so that writing an
optimisation back (:meth:`CloudStore.commit_poses`) updates the poses of the keyframes it moved
and only the positions of the points it moved relative to them (a full BA's; a pose graph
moves points rigidly with their keyframe). Every write takes what the atlas changed since the
last one (:attr:`Atlas.unsaved`) and the bookkeeping tables that changed.
"""

from __future__ import annotations

import logging
import sqlite3
import weakref
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from services.cloud.atlas.atlas import (
    Atlas,
    AtlasState,
    KeyframeView,
    LoopEdge,
    MapPointView,
    MergeRecord,
    RetiredKeyframe,
)
from services.cloud.atlas.atlas_records import Unsaved
from services.cloud.store.persistence_schema import (
    DB_NAME,
    SCHEMA,
    SCHEMA_VERSION,
    UPGRADABLE,
    PersistenceError,
    arr,
    pack,
    pack_state,
    unpack,
    unpack_point,
    unpack_pose,
    unpack_state,
    upgrade,
    write_state,
)

log = logging.getLogger(__name__)

FIRST_MISSION = "mission-0"
"""The name of a state directory's first mission when none was given."""


class CloudStore:
    """The cloud's state directory (``<state_dir>/cloud.sqlite``; None: in memory)."""

    def __init__(self, state_dir: str | Path | None) -> None:
        # None: an in-memory database (tests, replays): the same schema, nothing kept
        self.path = Path(":memory:") if state_dir is None else Path(state_dir) / DB_NAME
        try:
            if state_dir is not None:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(str(self.path), isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE name='schema'").fetchone()
        except sqlite3.DatabaseError as exc:
            raise PersistenceError(
                f"{self.path}: not a usable cloud state database ({exc})"
            ) from exc
        if row is None:
            self._db.execute("INSERT INTO meta VALUES ('schema', ?)", (SCHEMA_VERSION,))
        elif row[0] in UPGRADABLE:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                upgrade(self._db, int(row[0]))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            log.info("%s: upgraded schema %d -> %d", self.path, row[0], SCHEMA_VERSION)
        elif row[0] != SCHEMA_VERSION:
            raise PersistenceError(f"{self.path}: schema {row[0]}, expected {SCHEMA_VERSION}")
        self._db.execute("INSERT OR IGNORE INTO meta VALUES ('mission', 0)")
        self._db.execute("INSERT OR IGNORE INTO missions VALUES (0, ?)", (FIRST_MISSION,))
        self.mission = int(
            self._db.execute("SELECT value FROM meta WHERE name='mission'").fetchone()[0]
        )
        """The current mission's number (0, 1, ...; see :meth:`enter_mission`)."""
        # The atlas whose rows this store holds as they are, but for the atlas's unsaved
        # changes (then :meth:`save_all` writes only those); None: write it whole.
        self._kept: weakref.ref[Atlas] | None = None
        self._state: AtlasState | None = None  # the bookkeeping as the rows hold it (None: unknown)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> CloudStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writing
    def commit(
        self,
        atlas: Atlas,
        keyframes: Iterable[int] = (),
        map_points: Iterable[int] = (),
        edge_sequences: Mapping[str, int] | None = None,
        positions: Mapping[str, tuple[bytes, int]] | None = None,
        agents: Mapping[int, tuple[str, str, int]] | None = None,
        sensors: Mapping[str, bytes] | None = None,
    ) -> None:
        """In one transaction: write the given keyframes and map points as the atlas holds them
        (rows of keys no longer in the atlas are deleted) and whatever else the atlas changed
        since the last write (:attr:`Atlas.unsaved`), the atlas bookkeeping, the last
        delivered sequence of each edge, the transport ``positions`` ``{edge: (stream id,
        last delivered seq)}`` (replacing the stored ones), ``agents`` ``{agent id: (robot
        name, edge id, edge map id)}`` and ``sensors`` ``{robot name: its encoded sensor
        description}``. Returns once the data is durable."""
        u = atlas.unsaved.take()
        u.keyframes.update(int(k) for k in keyframes)
        u.points.update(int(k) for k in map_points)
        self._transaction(atlas, u, edge_sequences, positions, agents, sensors)

    def commit_poses(
        self, atlas: Atlas, keyframes: Iterable[int] = (), map_points: Iterable[int] = ()
    ) -> None:
        """After an optimisation, in one transaction: what it changed (:attr:`Atlas.unsaved`:
        the poses of the keyframes it moved, the positions of the points it moved relative
        to their reference keyframe; points that only followed theirs keep their rows), the
        poses of ``keyframes`` and positions of ``map_points``, and the bookkeeping."""
        u = atlas.unsaved.take()
        u.poses.update(int(k) for k in keyframes)
        u.positions.update(int(k) for k in map_points)
        self._transaction(atlas, u)

    def save_all(
        self,
        atlas: Atlas,
        edge_sequences: Mapping[str, int] | None = None,
        positions: Mapping[str, tuple[bytes, int]] | None = None,
        agents: Mapping[int, tuple[str, str, int]] | None = None,
    ) -> None:
        """Make the stored atlas the atlas (after a merge, an optimisation or MBP) in one
        transaction, with the bookkeeping as :meth:`commit` writes it.

        The first time for an atlas (or after a failed write) every row is written and stale
        ones deleted; after that, and for the atlas :meth:`load` built, only what the atlas
        changed since (:attr:`Atlas.unsaved`: whole rows of keyframes and points whose
        observations, state or map changed, pose / position columns of those that only
        moved, deletions), so that its cost follows the change, not the atlas."""
        whole = self._kept is None or self._kept() is not atlas
        u = atlas.unsaved.take()
        if whole:
            u.keyframes.update(r[0] for r in self._db.execute("SELECT key FROM keyframes"))
            u.keyframes.update(atlas.keyframe_keys())
            u.points.update(r[0] for r in self._db.execute("SELECT key FROM map_points"))
            u.points.update(atlas.map_point_keys())
        self._transaction(atlas, u, edge_sequences, positions, agents, whole=whole)
        self._kept = weakref.ref(atlas)

    def _transaction(
        self,
        atlas: Atlas,
        u: Unsaved,
        edge_sequences: Mapping[str, int] | None = None,
        positions: Mapping[str, tuple[bytes, int]] | None = None,
        agents: Mapping[int, tuple[str, str, int]] | None = None,
        sensors: Mapping[str, bytes] | None = None,
        whole: bool = False,
    ) -> None:
        """Write ``u`` (taken from the atlas; given back to it if the write fails) and the
        rest in one transaction; ``whole``: every bookkeeping table too."""
        db = self._db
        st = atlas.state()
        db.execute("BEGIN IMMEDIATE")
        try:
            removed = self._write_points(atlas, sorted(u.keyframes), sorted(u.points))
            self._write_poses(atlas, sorted(u.poses - u.keyframes))
            self._write_positions(atlas, sorted(u.positions - u.points))
            last = None if whole else self._state
            write_state(db, st, last, removals=removed or whole)
            self._write_links(edge_sequences, positions, agents)
            for name, blob in (sensors or {}).items():
                db.execute(
                    "INSERT OR REPLACE INTO robot_sensors VALUES (?, ?)", (str(name), bytes(blob))
                )
            db.execute("COMMIT")
        except BaseException:
            self._rollback()
            atlas.unsaved.update(u)  # still to be written
            self._kept = self._state = None  # the next save_all is whole
            raise
        self._state = st

    def _write_links(
        self,
        edge_sequences: Mapping[str, int] | None,
        positions: Mapping[str, tuple[bytes, int]] | None,
        agents: Mapping[int, tuple[str, str, int]] | None,
    ) -> None:
        """The edges' sequences and transport positions, and the agents' rows (see
        :meth:`commit`)."""
        db = self._db
        for edge_id, seq in (edge_sequences or {}).items():
            db.execute(
                "INSERT INTO edge_sequences VALUES (?, ?) ON CONFLICT(edge_id) DO UPDATE "
                "SET last_seq = max(last_seq, excluded.last_seq)",
                (str(edge_id), int(seq)),
            )
        for edge_id, (stream_id, seq) in (positions or {}).items():
            db.execute(
                "INSERT OR REPLACE INTO edge_positions VALUES (?, ?, ?)",
                (str(edge_id), bytes(stream_id), int(seq)),
            )
        for agent, (name, edge_id, edge_map) in (agents or {}).items():
            db.execute(  # agents are created and changed in the current mission only
                "INSERT OR REPLACE INTO agent_names VALUES (?, ?, ?, ?, ?)",
                (int(agent), str(name), str(edge_id), int(edge_map), self.mission),
            )

    def _write_poses(self, atlas: Atlas, keyframes: Iterable[int]) -> None:
        """Only the poses, map ids and states of these keyframes (those the atlas still
        holds): not their features."""
        rows = []
        for k in keyframes:
            if atlas.has_keyframe(k):
                pose, map_id, v, bg, ba = atlas.keyframe_state(k)
                rows.append((np.asarray(pose, "<f8").tobytes(), map_id, pack_state(v, bg, ba), k))
        self._db.executemany(
            "UPDATE keyframes SET pose = ?, map_id = ?, state = ? WHERE key = ?", rows
        )

    def _write_positions(self, atlas: Atlas, map_points: Iterable[int]) -> None:
        """Only the positions of these map points (those the atlas still holds)."""
        self._db.executemany(
            "UPDATE map_points SET p = ?, in_ref = ? WHERE key = ?",
            atlas.map_point_position_rows(map_points),
        )

    def _rollback(self) -> None:
        """Undo the open transaction, if SQLite has not already (it rolls back by itself on
        e.g. a full disk, and a second ROLLBACK would hide the real error)."""
        if self._db.in_transaction:
            self._db.execute("ROLLBACK")

    def _write_points(
        self, atlas: Atlas, keyframes: Iterable[int], map_points: Iterable[int]
    ) -> bool:
        """Write (or delete) the rows of these keyframes and map points; True if a keyframe
        row was deleted."""
        db = self._db
        removed = False
        for key in keyframes:
            key = int(key)
            if not atlas.has_keyframe(key):
                db.execute("DELETE FROM keyframes WHERE key = ?", (key,))
                removed = True
                continue
            v = atlas.keyframe(key)
            blob = pack(
                velocity=v.velocity,
                bias_gyro=v.bias_gyro,
                bias_accel=v.bias_accel,
                keypoints=v.keypoints,
                levels=v.levels,
                descriptors=v.descriptors,
                word_ids=v.word_ids,
                map_point_keys=v.map_point_keys,
                virtual=v.virtual,
            )
            db.execute(
                "INSERT OR REPLACE INTO keyframes VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    key,
                    v.agent_id,
                    v.keyframe_id,
                    v.map_id,
                    v.timestamp,
                    np.asarray(v.T_map_body, "<f8").tobytes(),
                    blob,
                    pack_state(v.velocity, v.bias_gyro, v.bias_accel),
                ),
            )
        # Each point once, in one executemany each (a commit can touch thousands: every
        # point a keyframe observes, every point that follows a moved keyframe).
        keys = list(dict.fromkeys(int(k) for k in map_points))
        gone = [(k,) for k in keys if not atlas.has_map_point(k)]
        if gone:
            db.executemany("DELETE FROM map_points WHERE key = ?", gone)
        db.executemany(
            "INSERT OR REPLACE INTO map_points VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            atlas.map_point_rows(keys),
        )
        return removed

    # ------------------------------------------------------------------ missions
    def enter_mission(self, name: str) -> tuple[int, bool]:
        """Make mission ``name`` current: ``(its number, whether it was started now)``.

        The current mission of that name is resumed (nothing changes), and so is a current
        mission without agents yet (it takes the name); a name never used
        starts a new mission in one transaction: it becomes current, and the stored edge
        positions are cleared (the new mission's edges start their streams afresh; the old
        ones' replays would land in the new mission's agents). PersistenceError for the name
        of an earlier mission (its agents are the prior map now and cannot be continued)."""
        if not name:
            raise PersistenceError("a mission needs a name")
        row = self._db.execute("SELECT mission FROM missions WHERE name = ?", (name,)).fetchone()
        if row is not None:
            if int(row[0]) != self.mission:
                raise PersistenceError(
                    f"{self.path}: mission {name!r} ended (the current one is "
                    f"{self.missions()[self.mission]!r}); start a new mission with a new name"
                )
            return self.mission, False
        db = self._db
        used = db.execute("SELECT 1 FROM agent_names WHERE mission = ?", (self.mission,))
        if used.fetchone() is None:  # the current mission never had an agent: it is this one
            db.execute("UPDATE missions SET name = ? WHERE mission = ?", (name, self.mission))
            return self.mission, False
        number = self.mission + 1
        db.execute("BEGIN IMMEDIATE")
        try:
            db.execute("INSERT INTO missions VALUES (?, ?)", (number, name))
            db.execute("UPDATE meta SET value = ? WHERE name = 'mission'", (number,))
            db.execute("DELETE FROM edge_positions")
            db.execute("DELETE FROM edge_sequences")
            db.execute("COMMIT")
        except BaseException:
            self._rollback()
            raise
        self.mission = number
        log.info("%s: mission %d %r started", self.path, number, name)
        return number, True

    def missions(self) -> dict[int, str]:
        """``{mission number: name}``."""
        return {int(m): str(n) for m, n in self._db.execute("SELECT mission, name FROM missions")}

    def agent_missions(self) -> dict[int, int]:
        """``{agent id: its mission's number}``."""
        return {
            int(a): int(m) for a, m in self._db.execute("SELECT agent, mission FROM agent_names")
        }

    # ------------------------------------------------------------------ reading
    def last_sequences(self) -> dict[str, int]:
        """Last delivered (and durable) message sequence per edge id."""
        return {e: s for e, s in self._db.execute("SELECT edge_id, last_seq FROM edge_sequences")}

    def positions(self) -> dict[str, tuple[bytes, int]]:
        """Transport inbound position per edge: ``{edge: (stream id, last delivered seq)}``."""
        rows = self._db.execute("SELECT edge_id, stream_id, last_seq FROM edge_positions")
        return {e: (bytes(s), int(q)) for e, s, q in rows}

    def agents(self) -> dict[int, tuple[str, str, int]]:
        """Known agents: ``{agent id: (robot name, edge id, edge map id)}``."""
        rows = self._db.execute("SELECT agent, name, edge_id, edge_map FROM agent_names")
        return {int(a): (str(n), str(e), int(m)) for a, n, e, m in rows}

    def sensors(self) -> dict[str, bytes]:
        """Each robot's encoded sensor description: ``{robot name: bytes}``."""
        rows = self._db.execute("SELECT name, sensors FROM robot_sensors")
        return {str(n): bytes(b) for n, b in rows}

    def load(self) -> Atlas:
        """Rebuild the atlas stored in this directory (empty atlas for a new directory)."""
        db = self._db
        try:
            kfs = []
            for key, agent, kf_id, map_id, ts, pose, blob, state in db.execute(
                "SELECT key, agent, keyframe_id, map_id, timestamp, pose, data, state "
                "FROM keyframes ORDER BY key"
            ):
                d = {**unpack(blob), "T_map_body": unpack_pose(pose)}
                if state is not None:  # (schema 9: refreshed without the features)
                    d.update(unpack_state(state))
                kfs.append(
                    KeyframeView(
                        key=key, agent_id=agent, keyframe_id=kf_id, map_id=map_id, timestamp=ts, **d
                    )
                )
            T_ref = {v.key: v.T_map_body for v in kfs}
            mps = []
            for key, agent, mp_id, map_id, ref, p, blob, in_ref in db.execute(
                "SELECT key, agent, map_point_id, map_id, ref_kf, p, data, in_ref FROM map_points"
            ):
                d = unpack_point(p, blob)
                if in_ref:  # in its reference keyframe's frame
                    T = T_ref[ref]
                    d["p_map"] = T[:3, :3] @ d["p_map"] + T[:3, 3]
                mps.append(
                    MapPointView(
                        key=key, agent_id=agent, map_point_id=mp_id, map_id=map_id, ref_kf=ref, **d
                    )
                )
            agents = list(db.execute("SELECT agent, map_id, T_map_agent FROM agents"))
            merges = tuple(
                MergeRecord(t, s, arr(T), q, c, f)
                for t, s, T, q, c, f in db.execute(
                    "SELECT target_map, source_map, T, query_key, candidate_key, fused "
                    "FROM merges ORDER BY seq"
                )
            )
            loops = tuple(
                LoopEdge(a, b, arr(T), bool(i))
                for a, b, T, i in db.execute(
                    "SELECT key_a, key_b, T, inter_agent FROM loops ORDER BY seq"
                )
            )
            state = AtlasState(
                map_of_agent={a: m for a, m, _ in agents},
                T_map_agent={a: arr(T) for a, _, T in agents},
                merges=merges,
                loops=loops,
                removed_keyframes=frozenset(
                    r[0] for r in db.execute("SELECT key FROM removed_keyframes")
                ),
                aliases=dict(db.execute("SELECT dropped, kept FROM aliases")),
                retired=tuple(
                    RetiredKeyframe(
                        k, a, t, n, unpack_pose(T), o, None if To is None else unpack_pose(To), w
                    )
                    for k, a, t, n, T, o, To, w in db.execute(
                        "SELECT key, agent, timestamp, anchor, T, other, T_other, w_other "
                        "FROM retired_keyframes"
                    )
                ),
            )
        except (sqlite3.DatabaseError, ValueError, KeyError, TypeError) as exc:
            raise PersistenceError(f"{self.path}: corrupt cloud state ({exc})") from exc
        atlas = Atlas.restore(kfs, mps, state)
        self._kept = weakref.ref(atlas)
        self._state = atlas.state()
        log.info("loaded %d keyframes, %d map points from %s", len(kfs), len(mps), self.path)
        return atlas
