"""The cloud store's SQLite schema, its upgrades and its row formats (see
:mod:`services.cloud.store.persistence`, which reads and writes through these).

Keyframe arrays are ``.npy`` payloads (``numpy.save``, no pickle) inside an uncompressed
``.npz`` blob per row. Map point rows use a flat little-endian blob for their observations:
``(M, 2)`` ``<i8`` rows ``(keyframe key, keypoint index)``. A map point's position ``p``
(3 ``<f8``) is in its reference keyframe's body frame when ``in_ref`` is 1 (the point then
follows that keyframe: a pose graph that moves keyframes rewrites their poses, not their
points), else in its map's frame. A keyframe's ``state`` column (9 ``<f8``: velocity, gyro
and accelerometer biases) overrides those of its ``data`` blob when set: the edge refreshes a
keyframe's state many times, and that rewrites 72 bytes, not the features. A keyframe's
``map_point_keys`` in ``data`` are not read back (the map points' observations rebuild them),
so a new observation of a keyframe rewrites only the point's row.
"""

from __future__ import annotations

import io
import sqlite3

import numpy as np

from common.errors import RecslamError
from services.cloud.atlas.map_types import AliasSnapshot, AtlasState

DB_NAME = "cloud.sqlite"
SCHEMA_VERSION = 9
# Older schemas this one upgrades when it opens them (:func:`upgrade`): 5 added
# ``robot_sensors`` (``SCHEMA`` creates it); 6 added ``missions`` and the ``mission`` column of
# ``agent_names`` and keys that table by (mission, edge, robot, edge map), not (robot, edge
# map), so that several edges' and missions' agents stay apart (the table is rebuilt, its old
# rows are mission 0); 7 added ``map_points.in_ref`` (old rows: 0, positions in the map frame);
# 8 added ``retired_keyframes.other``, ``T_other`` and ``w_other`` (old rows: no blend); 9
# added ``keyframes.state`` (old rows: NULL, the state in ``data``).
UPGRADABLE = (3, 4, 5, 6, 7, 8)

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    key INTEGER PRIMARY KEY, agent INTEGER NOT NULL, keyframe_id INTEGER NOT NULL,
    map_id INTEGER NOT NULL, timestamp REAL NOT NULL, pose BLOB NOT NULL, data BLOB NOT NULL,
    state BLOB);
CREATE TABLE IF NOT EXISTS map_points (
    key INTEGER PRIMARY KEY, agent INTEGER NOT NULL, map_point_id INTEGER NOT NULL,
    map_id INTEGER NOT NULL, ref_kf INTEGER NOT NULL, p BLOB NOT NULL,
    data BLOB NOT NULL, in_ref INTEGER NOT NULL DEFAULT 0);
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
    timestamp REAL NOT NULL, anchor INTEGER NOT NULL, T BLOB NOT NULL, other INTEGER,
    T_other BLOB, w_other REAL NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS edge_sequences (edge_id TEXT PRIMARY KEY, last_seq INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS edge_positions (edge_id TEXT PRIMARY KEY, stream_id BLOB NOT NULL,
    last_seq INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS agent_names (agent INTEGER PRIMARY KEY, name TEXT NOT NULL,
    edge_id TEXT NOT NULL, edge_map INTEGER NOT NULL, mission INTEGER NOT NULL DEFAULT 0,
    UNIQUE (mission, edge_id, name, edge_map));
CREATE TABLE IF NOT EXISTS robot_sensors (name TEXT PRIMARY KEY, sensors BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS missions (mission INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE);
"""


class PersistenceError(RecslamError):
    """Unreadable or incompatible state directory."""


def pack(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def unpack(blob: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def unpack_point(p: bytes, blob: bytes) -> dict[str, np.ndarray]:
    """A map point row's position (as stored: see ``in_ref``) and observations."""
    if len(p) != 24 or len(blob) % 16:
        raise ValueError(f"map point position of {len(p)} bytes, observations of {len(blob)}")
    obs = np.frombuffer(blob, "<i8").reshape(-1, 2).astype(np.int64)
    return {
        "p_map": np.frombuffer(p, "<f8", 3).astype(np.float64),
        "obs_keyframes": obs[:, 0].copy(),
        "obs_indices": obs[:, 1].copy(),
    }


def unpack_pose(blob: bytes) -> np.ndarray:
    if len(blob) != 128:
        raise ValueError(f"keyframe pose of {len(blob)} bytes")
    return np.frombuffer(blob, "<f8").reshape(4, 4).astype(np.float64)


def pack_state(velocity: np.ndarray, bias_gyro: np.ndarray, bias_accel: np.ndarray) -> bytes:
    """A keyframe's ``state`` column."""
    return np.concatenate([velocity, bias_gyro, bias_accel]).astype("<f8").tobytes()


def unpack_state(blob: bytes) -> dict[str, np.ndarray]:
    if len(blob) != 72:
        raise ValueError(f"keyframe state of {len(blob)} bytes")
    v = np.frombuffer(blob, "<f8").astype(np.float64)
    return {"velocity": v[:3], "bias_gyro": v[3:6], "bias_accel": v[6:]}


def arr(blob: bytes) -> np.ndarray:
    return unpack(blob)["a"]


def upgrade(db: sqlite3.Connection, version: int) -> None:
    """Bring a schema-``version`` database (one of :data:`UPGRADABLE`) to
    :data:`SCHEMA_VERSION`, inside the caller's transaction."""
    if version < 6:
        # SQLite cannot change a table's constraints in place: rebuild it, keeping its rows.
        db.execute(
            "CREATE TABLE agent_names_v6 (agent INTEGER PRIMARY KEY, name TEXT NOT NULL, "
            "edge_id TEXT NOT NULL, edge_map INTEGER NOT NULL, "
            "mission INTEGER NOT NULL DEFAULT 0, UNIQUE (mission, edge_id, name, edge_map))"
        )
        db.execute(
            "INSERT INTO agent_names_v6 SELECT agent, name, edge_id, edge_map, 0 FROM agent_names"
        )
        db.execute("DROP TABLE agent_names")
        db.execute("ALTER TABLE agent_names_v6 RENAME TO agent_names")
    if version < 7:
        cols = [r[1] for r in db.execute("PRAGMA table_info(map_points)")]
        if "in_ref" not in cols:
            db.execute("ALTER TABLE map_points ADD COLUMN in_ref INTEGER NOT NULL DEFAULT 0")
    if version < 8:
        cols = [r[1] for r in db.execute("PRAGMA table_info(retired_keyframes)")]
        for name, decl in (("other", "INTEGER"), ("T_other", "BLOB"), ("w_other", "REAL")):
            if name not in cols:
                default = " NOT NULL DEFAULT 0" if name == "w_other" else ""
                db.execute(f"ALTER TABLE retired_keyframes ADD COLUMN {name} {decl}{default}")
    if version < 9:
        cols = [r[1] for r in db.execute("PRAGMA table_info(keyframes)")]
        if "state" not in cols:
            db.execute("ALTER TABLE keyframes ADD COLUMN state BLOB")
    db.execute("UPDATE meta SET value = ? WHERE name='schema'", (SCHEMA_VERSION,))


def write_state(
    db: sqlite3.Connection, st: AtlasState, last: AtlasState | None, removals: bool
) -> None:
    """The atlas bookkeeping ``st``, given ``last``, the state the rows hold (None: unknown,
    every table is rewritten): only the tables that changed, merges, loops and aliases by
    appending when ``st`` extends ``last`` (they grow by one record per loop or merge and
    are thousands of rows in a long mission). The removed and retired keyframes only with
    ``removals`` (they change only when a keyframe goes: MBP, or the edge culling one)."""
    if last is None or not _same_agents(st, last):
        db.execute("DELETE FROM agents")
        db.executemany(
            "INSERT INTO agents VALUES (?, ?, ?)",
            [(a, st.map_of_agent[a], pack(a=st.T_map_agent[a])) for a in st.map_of_agent],
        )
    old_merges = _kept_prefix(db, "merges", st.merges, None if last is None else last.merges)
    rows = []
    for i, m in enumerate(st.merges[old_merges:], start=old_merges):
        T, ends = pack(a=m.T_target_source), (m.query_key, m.candidate_key, m.fused_points)
        rows.append((i, m.target_map, m.source_map, T, *ends))
    db.executemany("INSERT INTO merges VALUES (?, ?, ?, ?, ?, ?, ?)", rows)
    old_loops = _kept_prefix(db, "loops", st.loops, None if last is None else last.loops)
    db.executemany(
        "INSERT INTO loops VALUES (?, ?, ?, ?, ?)",
        [
            (i, e.key_a, e.key_b, pack(a=e.T_a_b), int(e.inter_agent))
            for i, e in enumerate(st.loops[old_loops:], start=old_loops)
        ],
    )
    new = _new_aliases(st, last)
    if new is None:
        db.execute("DELETE FROM aliases")
        new = list(st.aliases.items())
    db.executemany("INSERT OR REPLACE INTO aliases VALUES (?, ?)", new)
    if not removals:
        return
    db.executemany(
        "INSERT OR IGNORE INTO removed_keyframes VALUES (?)", [(k,) for k in st.removed_keyframes]
    )
    db.execute("DELETE FROM retired_keyframes")
    db.executemany(
        "INSERT INTO retired_keyframes VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
        [
            (
                r.key,
                r.agent_id,
                r.timestamp,
                r.anchor,
                np.asarray(r.T_anchor_body, "<f8").tobytes(),
                r.other,
                None if r.T_other_body is None else np.asarray(r.T_other_body, "<f8").tobytes(),
                r.w_other,
            )
            for r in st.retired
        ],
    )


def _new_aliases(st: AtlasState, last: AtlasState | None) -> list[tuple[int, int]] | None:
    """The aliases ``st`` assigned since ``last``, from the atlas' log (no pass over every
    alias); None when ``last`` is not an earlier snapshot of the same atlas (rewrite them
    all: a store's ``last`` is the state it wrote or loaded, see ``CloudStore``)."""
    if last is None or not isinstance(st.aliases, AliasSnapshot):
        return None
    return st.aliases.since(last.aliases)


def _same_agents(st: AtlasState, last: AtlasState) -> bool:
    if last.map_of_agent != st.map_of_agent or last.T_map_agent.keys() != st.T_map_agent.keys():
        return False
    return all(np.array_equal(T, last.T_map_agent[a]) for a, T in st.T_map_agent.items())


def _kept_prefix(db: sqlite3.Connection, table: str, now: tuple, last: tuple | None) -> int:
    """How many of ``now``'s records the table keeps as they are: all of ``last`` when
    ``now`` starts with the same records (the atlas keeps them: identity), else none (the
    table is emptied)."""
    n = 0 if last is None else len(last)
    if last is not None and len(now) >= n and all(a is b for a, b in zip(now, last, strict=False)):
        return n
    db.execute(f"DELETE FROM {table}")
    return 0
