"""Keypoint coding for keyframes (intra) and non-keyframes (predictive).

Keyframe keypoints ``[x_l, y_l, l, angle_bin]`` arrive in canonical order (level, then
raster order in the level image). Per level: the feature count, then the gaps between
consecutive raster indices ``y_l * W_l + x_l`` with a geometric model whose mean the encoder
picks (sent as a scale index), then the angle bins (uniform). Sorting removes the
``log2(N!)`` bits of an arbitrary order, which is most of a keypoint's cost.

Continuation links (which previous track a keyframe feature continues): a binary flag per
feature (adaptive across frames), then for linked features the *rank* of the linked track
among all previous tracks sorted by squared distance (quarter-pixel integers, ties by
index; tracks of another pyramid level rank after all of the same level) from the keyframe
keypoint (rank 0 has its own adaptive flag), after moving the previous tracks by an affine
flow model fitted to the links (sent as 6 integers): almost always 0.

Non-keyframes: survival flags of the previous tracks (adaptive binary), then the survivors'
new positions predicted from their previous positions by a per-frame affine flow model in
fixed point (sent: 6 integers), residuals coded with per-axis discrete Laplace models
(scales sent), levels inherited from the track (one flag says so; otherwise coded), then
new tracks (count, level, position uniform over the grid).
"""

from __future__ import annotations

import numpy as np

from common.codec.entropy import N_SCALES, P_MIN, BitReader, BitWriter, best_scale_index
from common.codec.errors import CodecError
from common.codec.types import CodecConfig

AFFINE_SHIFT = 14  # linear terms of the flow model in units of 2**-14
AFFINE_SCALE_INDEX = 40  # Laplace scale 128 for the model's integers
MAX_RANK_ROWS = 1024


def kf_track_q(kp: np.ndarray, config: CodecConfig) -> np.ndarray:
    """Quarter-pixel (1/subpixel) integer level-0 positions ``(N, 2) int64`` of KF keypoints."""
    s = config.level_scale(kp[:, 2])
    return np.floor(kp[:, :2].astype(np.float64) * s[:, None] * config.subpixel + 0.5).astype(
        np.int64
    )


def _adaptive_p(counts: np.ndarray) -> float:
    return float(np.clip(counts[0] / counts[1], P_MIN, 1.0 - P_MIN))


# ---------------------------------------------------------------------- keyframe keypoints
def encode_kf_keypoints(w: BitWriter, kp: np.ndarray, config: CodecConfig) -> None:
    for level in range(config.n_levels):
        sel = kp[kp[:, 2] == level]
        w.put_count(sel.shape[0], "keypoint")
        if sel.shape[0] == 0:
            continue
        width, _ = config.level_size(level)
        lin = sel[:, 1].astype(np.int64) * width + sel[:, 0]
        gaps = np.diff(lin, prepend=0)
        si = best_scale_index(gaps, signed=False)
        w.put_uniform(np.array([si]), N_SCALES, "keypoint")
        w.put_geometric(gaps, si, "keypoint")
        w.put_uniform(sel[:, 3], config.angle_bins, "keypoint")


def decode_kf_keypoints(r: BitReader, config: CodecConfig) -> np.ndarray:
    parts = []
    total = 0
    for level in range(config.n_levels):
        n = r.get_count(config.max_features - total)
        total += n
        if n == 0:
            continue
        width, height = config.level_size(level)
        si = int(r.get_uniform(1, N_SCALES)[0])
        lin = np.cumsum(r.get_geometric(n, si))
        if lin[-1] >= width * height:
            raise CodecError(f"keypoint outside the level-{level} image")
        ang = r.get_uniform(n, config.angle_bins)
        parts.append(np.stack([lin % width, lin // width, np.full(n, level), ang], axis=1))
    if not parts:
        return np.zeros((0, 4), dtype=np.int32)
    return np.concatenate(parts).astype(np.int32)


# ---------------------------------------------------------------------- links
def _link_key(
    q: np.ndarray, lev: np.ndarray, tracks_q: np.ndarray, tracks_lev: np.ndarray
) -> np.ndarray:
    """Sort key of previous tracks for each query: other levels last, then squared distance."""
    d = q[:, None, :] - tracks_q[None, :, :]
    other = (lev[:, None] != tracks_lev[None, :]).astype(np.int64) << 50
    return (d * d).sum(axis=2) + other


def _sq_dist(q: np.ndarray, tracks_q: np.ndarray) -> np.ndarray:
    """Squared distances ``(R, T) int64`` (same values as :func:`_link_key`'s first term)."""
    dx = q[:, 0, None] - tracks_q[None, :, 0]
    dy = q[:, 1, None] - tracks_q[None, :, 1]
    return dx * dx + dy * dy


def _by_level_ok(q: np.ndarray, pred: np.ndarray) -> bool:
    """True when every squared distance is below 2**50, so that :func:`_link_key` orders
    the query's own level first and a per-level search gives the same ranks (cheaper)."""
    lim = 1 << 23
    return bool(np.abs(q).max(initial=0) < lim and np.abs(pred).max(initial=0) < lim)


def _ranks_full(
    q: np.ndarray, lev: np.ndarray, pred: np.ndarray, tracks_lev: np.ndarray, tgt: np.ndarray
) -> np.ndarray:
    """Ranks of the targets ``tgt (R,)`` among all previous tracks, by definition."""
    n_prev = pred.shape[0]
    ranks = np.zeros(tgt.size, dtype=np.int64)
    for s in range(0, tgt.size, MAX_RANK_ROWS):
        sl = slice(s, s + MAX_RANK_ROWS)
        d2 = _link_key(q[sl], lev[sl], pred, tracks_lev)
        t = tgt[sl]
        dl = d2[np.arange(t.size), t][:, None]
        before = (d2 < dl) | ((d2 == dl) & (np.arange(n_prev)[None, :] < t[:, None]))
        ranks[sl] = before.sum(axis=1)
    return ranks


def _link_ranks(
    q: np.ndarray, lev: np.ndarray, pred: np.ndarray, tracks_lev: np.ndarray, tgt: np.ndarray
) -> np.ndarray:
    """Rank of each target track (see module docstring) for queries ``q (R, 2)``."""
    if not _by_level_ok(q, pred):
        return _ranks_full(q, lev, pred, tracks_lev, tgt)
    ranks = np.zeros(tgt.size, dtype=np.int64)
    same = tracks_lev[tgt] == lev
    for level in np.unique(lev[same]):
        rows = np.flatnonzero(same & (lev == level))
        cand = np.flatnonzero(tracks_lev == level)  # ascending track index
        d2 = _sq_dist(q[rows], pred[cand])
        pos = np.searchsorted(cand, tgt[rows])
        dl = d2[np.arange(rows.size), pos][:, None]
        before = (d2 < dl) | ((d2 == dl) & (np.arange(cand.size)[None, :] < pos[:, None]))
        ranks[rows] = before.sum(axis=1)
    if not same.all():
        rows = np.flatnonzero(~same)
        ranks[rows] = _ranks_full(q[rows], lev[rows], pred, tracks_lev, tgt[rows])
    return ranks


def _links_of_ranks(
    q: np.ndarray, lev: np.ndarray, pred: np.ndarray, tracks_lev: np.ndarray, ranks: np.ndarray
) -> np.ndarray:
    """Inverse of :func:`_link_ranks`: the track of each rank (ranks < number of tracks)."""
    out = np.zeros(ranks.size, dtype=np.int64)
    todo = np.ones(ranks.size, dtype=bool)
    if _by_level_ok(q, pred):
        for level in np.unique(lev):
            cand = np.flatnonzero(tracks_lev == level)
            rows = np.flatnonzero((lev == level) & (ranks < cand.size))
            if rows.size == 0:
                continue
            d2 = _sq_dist(q[rows], pred[cand])
            pick = np.argmin(d2, axis=1)  # rank 0: the first minimum
            far = np.flatnonzero(ranks[rows] > 0)
            if far.size:
                order = np.argsort(d2[far], axis=1, kind="stable")
                pick[far] = order[np.arange(far.size), ranks[rows[far]]]
            out[rows] = cand[pick]
            todo[rows] = False
    rows = np.flatnonzero(todo)
    for s in range(0, rows.size, MAX_RANK_ROWS):
        r = rows[s : s + MAX_RANK_ROWS]
        key = _link_key(q[r], lev[r], pred, tracks_lev)
        order = np.argsort(key, axis=1, kind="stable")
        out[r] = order[np.arange(r.size), ranks[r]]
    return out


def encode_links(
    w: BitWriter,
    links: np.ndarray,
    q: np.ndarray,
    lev: np.ndarray,
    tracks_q: np.ndarray,
    tracks_lev: np.ndarray,
    counts: np.ndarray,
    config: CodecConfig,
) -> None:
    """``counts``: adaptive ``[linked, total, rank0, total_linked]``, updated in place."""
    n_prev = tracks_q.shape[0]
    if n_prev == 0 or links.size == 0:
        return
    linked = links >= 0
    w.put_bernoulli(linked.astype(np.int64), np.full(links.size, _adaptive_p(counts)), "link")
    counts[:2] += [float(linked.sum()), float(links.size)]
    idx = np.flatnonzero(linked)
    if idx.size == 0:
        return
    a = fit_affine(tracks_q[links[idx]], q[idx], config)
    w.put_signed(a, AFFINE_SCALE_INDEX, "link")
    pred = _affine_predict(tracks_q, a, config)
    ranks = _link_ranks(q[idx], lev[idx], pred, tracks_lev, links[idx].astype(np.int64))
    zero = ranks == 0
    w.put_bernoulli(zero.astype(np.int64), np.full(ranks.size, _adaptive_p(counts[2:])), "link")
    counts[2:] += [float(zero.sum()), float(ranks.size)]
    if not zero.all():
        si = best_scale_index(ranks[~zero] - 1, signed=False)
        w.put_uniform(np.array([si]), N_SCALES, "link")
        w.put_geometric(ranks[~zero] - 1, si, "link")


def decode_links(
    r: BitReader,
    n: int,
    q: np.ndarray,
    lev: np.ndarray,
    tracks_q: np.ndarray,
    tracks_lev: np.ndarray,
    counts: np.ndarray,
    config: CodecConfig,
) -> np.ndarray:
    links = np.full(n, -1, dtype=np.int64)
    n_prev = tracks_q.shape[0]
    if n_prev == 0 or n == 0:
        return links
    linked = r.get_bernoulli(np.full(n, _adaptive_p(counts))).astype(bool)
    counts[:2] += [float(linked.sum()), float(n)]
    idx = np.flatnonzero(linked)
    if idx.size == 0:
        return links
    a = r.get_signed(6, AFFINE_SCALE_INDEX)
    if np.abs(a).max() > (1 << 28):
        raise CodecError("link flow model out of range")
    pred = _affine_predict(tracks_q, a, config)
    zero = r.get_bernoulli(np.full(idx.size, _adaptive_p(counts[2:]))).astype(bool)
    counts[2:] += [float(zero.sum()), float(idx.size)]
    ranks = np.zeros(idx.size, dtype=np.int64)
    if not zero.all():
        si = int(r.get_uniform(1, N_SCALES)[0])
        ranks[~zero] = r.get_geometric(int((~zero).sum()), si) + 1
    if ranks.max() >= n_prev:
        raise CodecError(f"link rank {int(ranks.max())} beyond {n_prev} previous tracks")
    links[idx] = _links_of_ranks(q[idx], lev[idx], pred, tracks_lev, ranks)
    return links


# ---------------------------------------------------------------------- non-keyframes
def _affine_predict(prev_q: np.ndarray, a: np.ndarray, config: CodecConfig) -> np.ndarray:
    """Predicted positions (fixed point): ``prev + ((A @ [xc, yc]) >> 14) + t``."""
    cx = config.image_width * config.subpixel // 2
    cy = config.image_height * config.subpixel // 2
    xc, yc = prev_q[:, 0] - cx, prev_q[:, 1] - cy
    half = 1 << (AFFINE_SHIFT - 1)
    dx = (a[0] * xc + a[1] * yc + half) >> AFFINE_SHIFT
    dy = (a[3] * xc + a[4] * yc + half) >> AFFINE_SHIFT
    return prev_q + np.stack([dx + a[2], dy + a[5]], axis=1)


def fit_affine(prev_q: np.ndarray, cur_q: np.ndarray, config: CodecConfig) -> np.ndarray:
    """Robust least-squares affine flow in fixed point: ``(6,) int64``."""
    a = np.zeros(6, dtype=np.int64)
    n = prev_q.shape[0]
    if n == 0:
        return a
    d = (cur_q - prev_q).astype(np.float64)
    if n < 6:
        a[2], a[5] = np.round(np.median(d, axis=0)).astype(np.int64)
        return a
    cx = config.image_width * config.subpixel / 2
    cy = config.image_height * config.subpixel / 2
    m = np.stack([prev_q[:, 0] - cx, prev_q[:, 1] - cy, np.ones(n)], axis=1)
    keep = np.ones(n, dtype=bool)
    coef = np.zeros((3, 2))
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(m[keep], d[keep], rcond=None)
        res = np.abs(d - m @ coef).sum(axis=1)
        thr = max(3.0 * np.median(res), 2.0)
        new_keep = res <= thr
        if new_keep.sum() < 6 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    scale = float(1 << AFFINE_SHIFT)
    lim = 1 << 28
    vals = [
        coef[0, 0] * scale,
        coef[1, 0] * scale,
        coef[2, 0],
        coef[0, 1] * scale,
        coef[1, 1] * scale,
        coef[2, 1],
    ]
    return np.clip(np.round(np.nan_to_num(vals)), -lim, lim).astype(np.int64)


def _encode_positions(
    w: BitWriter, prev_q: np.ndarray, cur_q: np.ndarray, config: CodecConfig, a: np.ndarray
) -> None:
    """One group of survivors: its affine flow model ``a`` (:func:`fit_affine`), then
    per-axis Laplace residuals."""
    if prev_q.shape[0] == 0:
        return
    w.put_signed(a, AFFINE_SCALE_INDEX, "side")
    res = cur_q - _affine_predict(prev_q, a, config)
    for axis in range(2):
        si = best_scale_index(res[:, axis], signed=True)
        w.put_uniform(np.array([si]), N_SCALES, "side")
        w.put_signed(res[:, axis], si, "keypoint")


def _decode_positions(r: BitReader, prev_q: np.ndarray, config: CodecConfig) -> np.ndarray:
    """Inverse of :func:`_encode_positions`: the group's positions (n, 2) int64."""
    n = prev_q.shape[0]
    q = np.zeros((n, 2), dtype=np.int64)
    if n == 0:
        return q
    a = r.get_signed(6, AFFINE_SCALE_INDEX)
    if np.abs(a).max() > (1 << 28):
        raise CodecError("flow model out of range")
    pred = _affine_predict(prev_q, a, config)
    for axis in range(2):
        si = int(r.get_uniform(1, N_SCALES)[0])
        q[:, axis] = pred[:, axis] + r.get_signed(n, si)
    return q


def _fit(prev_q: np.ndarray, cur_q: np.ndarray, config: CodecConfig) -> tuple[np.ndarray, float]:
    """A group's affine flow and a proxy of its residuals' code length (``sum log2(1 + |r|)``,
    the cost's shape under a Laplace model, without coding them)."""
    if prev_q.shape[0] == 0:
        return np.zeros(6, np.int64), 0.0
    a = fit_affine(prev_q, cur_q, config)
    res = cur_q - _affine_predict(prev_q, a, config)
    return a, float(np.log2(1.0 + np.abs(res)).sum())


def _encode_levels(
    w: BitWriter, levels: np.ndarray, track_levels: np.ndarray, config: CodecConfig
) -> None:
    same = bool(np.array_equal(levels, track_levels))
    w.put_bernoulli(np.array([int(same)]), np.array([0.5]), "side")
    if not same:
        w.put_uniform(levels, config.n_levels, "keypoint")


def _decode_levels(r: BitReader, track_levels: np.ndarray, config: CodecConfig) -> np.ndarray:
    if bool(r.get_bernoulli(np.array([0.5]))[0]):
        return track_levels.copy()
    return r.get_uniform(len(track_levels), config.n_levels)


def _encode_new(w: BitWriter, q: np.ndarray, levels: np.ndarray, config: CodecConfig) -> None:
    if len(q):
        w.put_uniform(levels, config.n_levels, "new")
        w.put_uniform(q[:, 0], config.image_width * config.subpixel, "new")
        w.put_uniform(q[:, 1], config.image_height * config.subpixel, "new")


def _decode_new(r: BitReader, q: np.ndarray, levels: np.ndarray, config: CodecConfig) -> None:
    """Fill ``q`` (n, 2) and ``levels`` (n,) in place."""
    n = len(q)
    if n:
        levels[:] = r.get_uniform(n, config.n_levels)
        q[:, 0] = r.get_uniform(n, config.image_width * config.subpixel)
        q[:, 1] = r.get_uniform(n, config.image_height * config.subpixel)


def encode_non_keyframe(
    w: BitWriter,
    survived: np.ndarray,
    keypoints: np.ndarray,
    tracks_q: np.ndarray,
    tracks_level: np.ndarray,
    survival_counts: np.ndarray,
    config: CodecConfig,
    steps: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """A non-keyframe's body. Without ``steps`` (kind 2): one affine flow predicts every
    survivor. With ``steps = (tracks_v, tracks_has_v)`` (kind 5): the survivors whose track
    moved in the last coded frame may be predicted from there by their own last step
    (quarter px) plus an affine correction, when one flag says so (the encoder's choice of
    the cheaper): parallax makes each track's flow its own, and it changes little from one
    frame to the next (robot2 of the default dataset: ~5.1 -> ~3.0 bits a track)."""
    n_prev = tracks_q.shape[0]
    w.put_bernoulli(
        survived.astype(np.int64), np.full(n_prev, _adaptive_p(survival_counts)), "survival"
    )
    survival_counts += [float(survived.sum()), float(n_prev)]
    n_surv = int(survived.sum())
    n_new = keypoints.shape[0] - n_surv
    w.put_count(n_new, "new")
    cur_q = np.floor(keypoints[:, :2] * config.subpixel + 0.5).astype(np.int64)
    levels = keypoints[:, 2].astype(np.int64)
    if n_surv:
        prev_q, cur = tracks_q[survived], cur_q[:n_surv]
        a_all, cost_all = _fit(prev_q, cur, config)
        use = False
        if steps is not None:
            moved = steps[1][survived]
            stepped = prev_q + steps[0][survived]
            use = bool(moved.any())
            if use:
                a_moved, cost_moved = _fit(stepped[moved], cur[moved], config)
                a_rest, cost_rest = _fit(prev_q[~moved], cur[~moved], config)
                use = cost_moved + cost_rest < cost_all
            w.put_bernoulli(np.array([int(use)]), np.array([0.5]), "side")
        if use:
            _encode_positions(w, stepped[moved], cur[moved], config, a_moved)
            _encode_positions(w, prev_q[~moved], cur[~moved], config, a_rest)
        else:
            _encode_positions(w, prev_q, cur, config, a_all)
        _encode_levels(w, levels[:n_surv], tracks_level[survived], config)
    _encode_new(w, cur_q[n_surv:], levels[n_surv:], config)


def decode_non_keyframe(
    r: BitReader,
    tracks_q: np.ndarray,
    tracks_level: np.ndarray,
    survival_counts: np.ndarray,
    config: CodecConfig,
    steps: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_non_keyframe` (with its ``steps``): (survived (P,) bool,
    positions (N, 2) int64 quarter px, levels (N,))."""
    n_prev = tracks_q.shape[0]
    survived = r.get_bernoulli(np.full(n_prev, _adaptive_p(survival_counts))).astype(bool)
    survival_counts += [float(survived.sum()), float(n_prev)]
    n_surv = int(survived.sum())
    n_new = r.get_count(config.max_features - n_surv)
    q = np.zeros((n_surv + n_new, 2), dtype=np.int64)
    levels = np.zeros(n_surv + n_new, dtype=np.int64)
    if n_surv:
        prev_q = tracks_q[survived]
        use = steps is not None and bool(r.get_bernoulli(np.array([0.5]))[0])
        if use and steps is not None:
            moved = steps[1][survived]
            stepped = prev_q + steps[0][survived]
            q[:n_surv][moved] = _decode_positions(r, stepped[moved], config)
            q[:n_surv][~moved] = _decode_positions(r, prev_q[~moved], config)
        else:
            q[:n_surv] = _decode_positions(r, prev_q, config)
        levels[:n_surv] = _decode_levels(r, tracks_level[survived], config)
    _decode_new(r, q[n_surv:], levels[n_surv:], config)
    if np.abs(q).max(initial=0) > (1 << 40):
        raise CodecError("decoded keypoint out of range")
    return survived, q, levels


# ---------------------------------------------------------------------- carried descriptors
def encode_carried_rows(w: BitWriter, carried: np.ndarray) -> None:
    """Which features of a standalone keyframe carry the descriptor of a row of the
    receiver's previous keyframe (``carried`` (N,) int64, -1: none): their count, a flag per
    feature, then the rows as differences from the previous carried feature's (both lists
    are in canonical order, so continued features keep roughly the same order)."""
    on = carried >= 0
    w.put_flags(on, "link")
    if not on.any():
        return
    deltas = np.diff(np.concatenate([[-1], carried[on]]))
    si = best_scale_index(deltas, signed=True)
    w.put_uniform(np.array([si]), N_SCALES, "link")
    w.put_signed(deltas, si, "link")


def decode_carried_rows(r: BitReader, n: int) -> np.ndarray:
    """Inverse of :func:`encode_carried_rows`: (n,) int64, -1 where nothing is carried."""
    on = r.get_flags(n)
    k = int(on.sum())
    out = np.full(n, -1, np.int64)
    if k == 0:
        return out
    si = int(r.get_uniform(1, N_SCALES)[0])
    rows = np.cumsum(r.get_signed(k, si)) - 1
    if k and (rows.min() < 0 or rows.max() >= (1 << 24)):
        raise CodecError("carried row out of range")
    out[on] = rows
    return out
