"""Each robot's reference trajectory (ground truth) in the frame of the map it is in, for the
dashboard's overlay."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from common.evaluation.alignment import umeyama
from common.evaluation.association import match_timestamps
from common.evaluation.errors import EvaluationError
from common.evaluation.trajectory import Trajectory
from common.map_view import GroundTruth
from services.cloud.atlas.atlas import Atlas


def references_in_maps(
    atlas: Atlas,
    agents: Mapping[str, list[int]],
    references: Mapping[str, Trajectory],
    max_points: int = 3000,
    max_dt_ns: int = 20_000_000,
) -> tuple[GroundTruth, ...]:
    """The reference trajectory of each robot name in ``agents`` (its atlas agent ids) that
    ``references`` holds, in its map's frame: all robots of one map are aligned to it with
    one rigid transform (Umeyama on the keyframe positions associated by time within
    ``max_dt_ns``, 20 ms, by the evaluation's ``match_timestamps``), each robot through its
    agent with the most keyframes; maps with fewer than 3 such pairs are left out. At most
    ``max_points`` poses per robot."""
    in_atlas = set(atlas.agents())
    pairs: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    owner: dict[str, int] = {}
    for name, ids in agents.items():
        ids = [a for a in ids if a in in_atlas]
        if name not in references or not ids:
            continue
        ref = references[name]
        main_id = max(ids, key=lambda a: len(atlas.keyframe_keys(agent_id=a)))
        owner[name] = main_id
        kfs = sorted(
            map(atlas.keyframe, atlas.keyframe_keys(agent_id=main_id)), key=lambda kf: kf.timestamp
        )
        t_est_ns = np.array([round(kf.timestamp * 1e9) for kf in kfs], np.int64)
        i_est, i_ref = match_timestamps(t_est_ns, ref.timestamps_ns, max_dt_ns)
        p_est = np.array([kfs[i].T_map_body[:3, 3] for i in i_est]).reshape(-1, 3)
        pairs.setdefault(atlas.map_of_agent(main_id), []).append((ref.p_world_body[i_ref], p_est))
    align = {}
    for m, lst in pairs.items():
        p_ref = np.concatenate([a for a, _ in lst])
        p_est = np.concatenate([b for _, b in lst])
        if p_ref.shape[0] >= 3:
            try:
                align[m] = umeyama(p_ref, p_est)
            except EvaluationError:
                continue
    out = []
    for name, main_id in sorted(owner.items()):
        tf = align.get(atlas.map_of_agent(main_id))
        if tf is None:
            continue
        ref = references[name]
        step = max(1, len(ref.timestamps_ns) // max_points)
        out.append(
            GroundTruth(
                main_id, ref.timestamps_ns[::step] * 1e-9, tf.apply_points(ref.p_world_body[::step])
            )
        )
    return tuple(out)
