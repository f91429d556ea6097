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

Keyframe arrays are stored as ``.npy`` payloads (``numpy.save``, no pickle) inside an
uncompressed ``.npz`` blob per row. Map point rows (many, small, rewritten whenever an
observation is added) use a flat little-endian blob instead, ~40x cheaper to write:
``(M, 2)`` ``<i8`` rows ``(keyframe key, keypoint index)``. Keyframe poses (16 ``<f8``) and
map point positions (3 ``<f8``) have their own columns, so that writing an optimisation back
(:meth:`CloudStore.commit_poses`) is a cheap ``UPDATE`` of those columns only.
"""

from __future__ import annotations

import io
import logging
import sqlite3
import weakref
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from common.errors import RecslamError
from services.cloud.atlas import (
    Atlas,
    AtlasState,
    KeyframeView,
    LoopEdge,
    MapPointView,
    MergeRecord,
    RetiredKeyframe,
)

log = logging.getLogger(__name__)

DB_NAME = "cloud.sqlite"
SCHEMA_VERSION = 6
# Older schemas this one upgrades when it opens them: 5 added ``robot_sensors`` (``_SCHEMA``
# creates it); 6 added ``missions`` and the ``mission`` column of ``agent_names`` and keys that
# table by (mission, edge, robot, edge map), not (robot, edge map), so that several edges' and
# missions' agents stay apart (:func:`_migrate_agent_names`: the table is rebuilt, its old rows
# are mission 0).
_UPGRADABLE = (3, 4, 5)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    key INTEGER PRIMARY KEY, agent INTEGER NOT NULL, keyframe_id INTEGER NOT NULL,
    map_id INTEGER NOT NULL, timestamp REAL NOT NULL, pose BLOB NOT NULL, data BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS map_points (
    key INTEGER PRIMARY KEY, agent INTEGER NOT NULL, map_point_id INTEGER NOT NULL,
    map_id INTEGER NOT NULL, ref_kf INTEGER NOT NULL, p BLOB NOT NULL,
    data BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS agents (agent INTEGER PRIMARY KEY, map_id INTEGER NOT NULL,
    T_map_agent BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS merges (seq INTEGER PRIMARY KEY, target_map INTEGER NOT NULL,
    source_map INTEGER NOT NULL, T BLOB NOT NULL, query_key INTEGER NOT NULL,
    candidate_key INTEGER NOT NULL, fused INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS loops (seq INTEGER PRIMARY KEY, key_a INTEGER NOT NULL,
    key_b INTEGER NOT NULL, T BLOB NOT NULL, inter_agent INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS aliases (dropped INTEGER PRIMARY KEY, kept INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS removed_keyframes (key INTEGER PRIMARY KEY);
CREATE TABLE IF NOT EXISTS retired_keyframes (key INTEGER PRIMARY KEY, agent INTEGER NOT NULL,
    timestamp REAL NOT NULL, anchor INTEGER NOT NULL, T BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS edge_sequences (edge_id TEXT PRIMARY KEY, last_seq INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS edge_positions (edge_id TEXT PRIMARY KEY, stream_id BLOB NOT NULL,
    last_seq INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS agent_names (agent INTEGER PRIMARY KEY, name TEXT NOT NULL,
    edge_id TEXT NOT NULL, edge_map INTEGER NOT NULL, mission INTEGER NOT NULL DEFAULT 0,
    UNIQUE (mission, edge_id, name, edge_map));
CREATE TABLE IF NOT EXISTS robot_sensors (name TEXT PRIMARY KEY, sensors BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS missions (mission INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE);
"""

FIRST_MISSION = "mission-0"
"""The name of a state directory's first mission when none was given."""


class PersistenceError(RecslamError):
    """Unreadable or incompatible state directory."""


def _pack(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def _unpack(blob: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _unpack_point(p: bytes, blob: bytes) -> dict[str, np.ndarray]:
    if len(p) != 24 or len(blob) % 16:
        raise ValueError(f"map point position of {len(p)} bytes, observations of {len(blob)}")
    obs = np.frombuffer(blob, "<i8").reshape(-1, 2).astype(np.int64)
    return {
        "p_map": np.frombuffer(p, "<f8", 3).astype(np.float64),
        "obs_keyframes": obs[:, 0].copy(),
        "obs_indices": obs[:, 1].copy(),
    }


def _pose(blob: bytes) -> np.ndarray:
    if len(blob) != 128:
        raise ValueError(f"keyframe pose of {len(blob)} bytes")
    return np.frombuffer(blob, "<f8").reshape(4, 4).astype(np.float64)


def _arr(blob: bytes) -> np.ndarray:
    return _unpack(blob)["a"]


def _migrate_agent_names(db: sqlite3.Connection) -> None:
    """Rebuild ``agent_names`` with the schema-6 ``mission`` column (old rows: mission 0) and
    key UNIQUE(mission, edge_id, name, edge_map), keeping its rows (SQLite cannot change a
    table's constraints in place). Inside the caller's transaction."""
    db.execute(
        "CREATE TABLE agent_names_v6 (agent INTEGER PRIMARY KEY, name TEXT NOT NULL, "
        "edge_id TEXT NOT NULL, edge_map INTEGER NOT NULL, mission INTEGER NOT NULL DEFAULT 0, "
        "UNIQUE (mission, edge_id, name, edge_map))"
    )
    db.execute(
        "INSERT INTO agent_names_v6 SELECT agent, name, edge_id, edge_map, 0 FROM agent_names"
    )
    db.execute("DROP TABLE agent_names")
    db.execute("ALTER TABLE agent_names_v6 RENAME TO agent_names")


class CloudStore:
    """The cloud's state directory (``<state_dir>/cloud.sqlite``)."""

    def __init__(self, state_dir: str | Path) -> None:
        self.path = Path(state_dir) / DB_NAME
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE name='schema'").fetchone()
        except sqlite3.DatabaseError as exc:
            raise PersistenceError(
                f"{self.path}: not a usable cloud state database ({exc})"
            ) from exc
        if row is None:
            self._db.execute("INSERT INTO meta VALUES ('schema', ?)", (SCHEMA_VERSION,))
        elif row[0] in _UPGRADABLE:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                _migrate_agent_names(self._db)
                self._db.execute("UPDATE meta SET value = ? WHERE name='schema'", (SCHEMA_VERSION,))
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
        moved_points: Iterable[int] = (),
    ) -> None:
        """In one transaction: write the given keyframes and map points as the atlas holds them
        (rows of keys no longer in the atlas are deleted), the atlas bookkeeping, the last
        delivered sequence of each edge, the transport ``positions`` ``{edge: (stream id,
        last delivered seq)}`` (replacing the stored ones), ``agents`` ``{agent id: (robot
        name, edge id, edge map id)}`` and ``sensors`` ``{robot name: its encoded sensor
        description}``; of ``moved_points`` only the position (points that followed a moved
        keyframe). Returns once the data is durable."""
        keyframes, map_points = [int(k) for k in keyframes], [int(k) for k in map_points]
        moved_points = [int(k) for k in moved_points]
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            removed = self._write_points(atlas, keyframes, map_points)
            self._write_positions(atlas, moved_points)
            self._write_state(atlas.state(), removals=removed)
            self._write_links(edge_sequences, positions, agents)
            for name, blob in (sensors or {}).items():
                db.execute(
                    "INSERT OR REPLACE INTO robot_sensors VALUES (?, ?)", (str(name), bytes(blob))
                )
            db.execute("COMMIT")
        except BaseException:
            self._rollback()
            raise
        atlas.unsaved.forget(keyframes=keyframes, points=map_points, positions=moved_points)

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

    def commit_poses(
        self,
        atlas: Atlas,
        keyframes: Iterable[int],
        map_points: Iterable[int],
    ) -> None:
        """In one transaction: only the poses, positions and map ids of the given (existing)
        keyframes and map points, plus the atlas bookkeeping (after an optimisation)."""
        kf = [int(k) for k in keyframes if atlas.has_keyframe(int(k))]
        mp = [int(k) for k in map_points]
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            self._write_poses(atlas, kf)
            self._write_positions(atlas, mp)
            self._write_state(atlas.state())
            db.execute("COMMIT")
        except BaseException:
            self._rollback()
            raise
        atlas.unsaved.forget(poses=kf, positions=mp)

    def _write_poses(self, atlas: Atlas, keyframes: Iterable[int]) -> None:
        """Only the poses and map ids of these keyframes (those the atlas still holds)."""
        self._db.executemany(
            "UPDATE keyframes SET pose = ?, map_id = ? WHERE key = ?",
            [
                (
                    np.asarray(atlas.T_map_body(k), "<f8").tobytes(),
                    atlas.map_id_of_keyframe(k),
                    k,
                )
                for k in keyframes
                if atlas.has_keyframe(k)
            ],
        )

    def _write_positions(self, atlas: Atlas, map_points: Iterable[int]) -> None:
        """Only the positions of these map points (those the atlas still holds)."""
        mp = np.array([int(k) for k in map_points if atlas.has_map_point(int(k))], np.int64)
        if not mp.size:
            return
        P = np.ascontiguousarray(atlas.map_point_positions(mp), "<f8")
        self._db.executemany(
            "UPDATE map_points SET p = ? WHERE key = ?",
            [(P[i].tobytes(), k) for i, k in enumerate(mp.tolist())],
        )

    def _rollback(self) -> None:
        """Undo the open transaction, if SQLite has not already (it rolls back by itself on
        e.g. a full disk, and a second ROLLBACK would hide the real error)."""
        if self._db.in_transaction:
            self._db.execute("ROLLBACK")

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
        self._kept = None  # a failed write leaves the rows unknown: the next one is whole
        if whole:
            kf_keys, mp_keys = atlas.keyframe_keys(), atlas.map_point_keys()
            u.keyframes = {r[0] for r in self._db.execute("SELECT key FROM keyframes")}
            u.keyframes.update(kf_keys)
            u.points = {r[0] for r in self._db.execute("SELECT key FROM map_points")}
            u.points.update(mp_keys)
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            removed = self._write_points(atlas, sorted(u.keyframes), sorted(u.points))
            self._write_poses(atlas, sorted(u.poses - u.keyframes))
            self._write_positions(atlas, sorted(u.positions - u.points))
            self._write_state(atlas.state(), removals=removed or whole)
            self._write_links(edge_sequences, positions, agents)
            db.execute("COMMIT")
        except BaseException:
            self._rollback()
            raise
        self._kept = weakref.ref(atlas)

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
            blob = _pack(
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
                "INSERT OR REPLACE INTO keyframes VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    key,
                    v.agent_id,
                    v.keyframe_id,
                    v.map_id,
                    v.timestamp,
                    np.asarray(v.T_map_body, "<f8").tobytes(),
                    blob,
                ),
            )
        # Each point once, in one executemany each (a commit can touch thousands: every
        # point a keyframe observes, every point that follows a moved keyframe).
        keys = list(dict.fromkeys(int(k) for k in map_points))
        gone = [(k,) for k in keys if not atlas.has_map_point(k)]
        if gone:
            db.executemany("DELETE FROM map_points WHERE key = ?", gone)
        db.executemany(
            "INSERT OR REPLACE INTO map_points VALUES (?, ?, ?, ?, ?, ?, ?)",
            atlas.map_point_rows(keys),
        )
        return removed

    def _write_state(self, st: AtlasState, removals: bool = False) -> None:
        """The atlas bookkeeping; the removed and retired keyframes only with ``removals``
        (they change only when a keyframe goes: MBP, or the edge culling one)."""
        db = self._db
        for table in ("agents", "merges", "loops", "aliases"):
            db.execute(f"DELETE FROM {table}")
        db.executemany(
            "INSERT INTO agents VALUES (?, ?, ?)",
            [(a, st.map_of_agent[a], _pack(a=st.T_map_agent[a])) for a in st.map_of_agent],
        )
        db.executemany(
            "INSERT INTO merges VALUES (?, ?, ?, ?, ?, ?, ?)",
            [
                (
                    i,
                    m.target_map,
                    m.source_map,
                    _pack(a=m.T_target_source),
                    m.query_key,
                    m.candidate_key,
                    m.fused_points,
                )
                for i, m in enumerate(st.merges)
            ],
        )
        db.executemany(
            "INSERT INTO loops VALUES (?, ?, ?, ?, ?)",
            [
                (i, e.key_a, e.key_b, _pack(a=e.T_a_b), int(e.inter_agent))
                for i, e in enumerate(st.loops)
            ],
        )
        db.executemany("INSERT INTO aliases VALUES (?, ?)", list(st.aliases.items()))
        if not removals:
            return
        db.executemany(
            "INSERT OR IGNORE INTO removed_keyframes VALUES (?)",
            [(k,) for k in st.removed_keyframes],
        )
        db.execute("DELETE FROM retired_keyframes")
        db.executemany(
            "INSERT INTO retired_keyframes VALUES (?, ?, ?, ?, ?)",
            [
                (
                    r.key,
                    r.agent_id,
                    r.timestamp,
                    r.anchor,
                    np.asarray(r.T_anchor_body, "<f8").tobytes(),
                )
                for r in st.retired
            ],
        )

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
            for key, agent, kf_id, map_id, ts, pose, blob in db.execute(
                "SELECT key, agent, keyframe_id, map_id, timestamp, pose, data FROM keyframes "
                "ORDER BY key"
            ):
                d = {**_unpack(blob), "T_map_body": _pose(pose)}
                kfs.append(
                    KeyframeView(
                        key=key, agent_id=agent, keyframe_id=kf_id, map_id=map_id, timestamp=ts, **d
                    )
                )
            mps = []
            for key, agent, mp_id, map_id, ref, p, blob in db.execute(
                "SELECT key, agent, map_point_id, map_id, ref_kf, p, data FROM map_points"
            ):
                d = _unpack_point(p, blob)
                mps.append(
                    MapPointView(
                        key=key, agent_id=agent, map_point_id=mp_id, map_id=map_id, ref_kf=ref, **d
                    )
                )
            agents = list(db.execute("SELECT agent, map_id, T_map_agent FROM agents"))
            merges = tuple(
                MergeRecord(t, s, _arr(T), q, c, f)
                for t, s, T, q, c, f in db.execute(
                    "SELECT target_map, source_map, T, query_key, candidate_key, fused "
                    "FROM merges ORDER BY seq"
                )
            )
            loops = tuple(
                LoopEdge(a, b, _arr(T), bool(i))
                for a, b, T, i in db.execute(
                    "SELECT key_a, key_b, T, inter_agent FROM loops ORDER BY seq"
                )
            )
            state = AtlasState(
                map_of_agent={a: m for a, m, _ in agents},
                T_map_agent={a: _arr(T) for a, _, T in agents},
                merges=merges,
                loops=loops,
                removed_keyframes=frozenset(
                    r[0] for r in db.execute("SELECT key FROM removed_keyframes")
                ),
                aliases=dict(db.execute("SELECT dropped, kept FROM aliases")),
                retired=tuple(
                    RetiredKeyframe(k, a, t, n, _pose(T))
                    for k, a, t, n, T in db.execute(
                        "SELECT key, agent, timestamp, anchor, T FROM retired_keyframes"
                    )
                ),
            )
        except (sqlite3.DatabaseError, ValueError, KeyError, TypeError) as exc:
            raise PersistenceError(f"{self.path}: corrupt cloud state ({exc})") from exc
        atlas = Atlas.restore(kfs, mps, state)
        self._kept = weakref.ref(atlas)
        log.info("loaded %d keyframes, %d map points from %s", len(kfs), len(mps), self.path)
        return atlas
