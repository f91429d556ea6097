"""Vocabulary benchmark: training cost, file size, lookup throughput, codec cost and BoW
discrimination for several branching factors k and depths L.

Run: ``.venv/bin/python benchmarks/bench_vocabulary.py``; writes
``benchmarks/results/vocabulary.md``. Every vocabulary is trained on the same descriptors
as the default one (``recslam vocab train --images skimage``: scikit-image's bundled
photographs, independent of EuRoC) and evaluated on the real EuRoC excerpt (read in place).
"""

from __future__ import annotations

import argparse
import itertools
import logging
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from common.codec import FeatureDecoder, FeatureEncoder, KeyframeFeatures
from common.vocabulary import Vocabulary, VocabularyTrainingConfig
from common.vocabulary_training import collect_descriptors
from lab.datasets import euroc_micro_path

log = logging.getLogger("bench_vocabulary")
RESULTS = Path(__file__).resolve().parent / "results" / "vocabulary.md"
DEFAULT_DATASET = euroc_micro_path()
CONFIGS = ((10, 3), (10, 4), (16, 4), (10, 5), (8, 6))
DEFAULT_K, DEFAULT_DEPTH = 16, 4


def lookup_rate(vocab: Vocabulary, desc: np.ndarray) -> float:
    vocab.lookup(desc[:1000])
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        vocab.lookup(desc)
        best = min(best, time.perf_counter() - t0)
    return desc.shape[0] / best


def codec_intra_bits(vocab: Vocabulary, kfs: list[KeyframeFeatures]) -> dict[str, float]:
    enc, dec = FeatureEncoder(vocab), FeatureDecoder(vocab)
    parts: dict[str, float] = {}
    n = nbytes = 0
    for kf in kfs:
        payload = enc.encode_keyframe(kf)
        if not dec.decode(payload).equals(kf):
            raise AssertionError("round trip is not bit-exact")
        for k, v in enc.last_bits.items():
            parts[k] = parts.get(k, 0.0) + v
        n += len(kf)
        nbytes += len(payload)
    out = {k: v / n for k, v in parts.items()}
    out["total"] = 8 * nbytes / n
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    train, what = collect_descriptors(["skimage"])
    n_train = sum(d.shape[0] for d in train)
    files = sorted((args.dataset / "mav0/cam0/data").glob("*.png"))
    orb = cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=8)
    kfs, descs = [], []
    for i, f in enumerate(files):
        kps, d = orb.detectAndCompute(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), None)
        descs.append(d)
        if i % 5 == 0:
            kfs.append(KeyframeFeatures.from_cv(kps, d).canonical())
    all_desc = np.concatenate(descs)
    rows = []
    for k, depth in CONFIGS:
        t0 = time.perf_counter()
        voc = Vocabulary.train(train, VocabularyTrainingConfig(k=k, depth=depth), what)
        t_train = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "v.npz"
            voc.save(path)
            size = path.stat().st_size
        words = voc.lookup(all_desc)
        ham = np.bitwise_count(all_desc ^ voc.words[words]).sum(axis=1).mean()
        bows = [voc.bow(kf.descriptors) for kf in kfs]
        near = np.mean([Vocabulary.score(a, b) for a, b in itertools.pairwise(bows)])
        unrelated = np.mean([Vocabulary.score(b, voc.bow(t)) for b in bows for t in train[::24]])
        bits = codec_intra_bits(voc, kfs)
        rows.append(
            (k, depth, voc, size, t_train, lookup_rate(voc, all_desc), ham, near, unrelated, bits)
        )
        log.info("k=%d L=%d: %d words, %.1f bits/feature", k, depth, voc.n_words, bits["total"])
    lines = [
        "# Visual vocabulary",
        "",
        f"Training set: {what} — {n_train} ORB descriptors from {len(train)} images "
        "(`recslam vocab train --images skimage`), independent of every test sequence. "
        f"Evaluation: EuRoC excerpt `{args.dataset.name}`, {len(files)} frames, "
        f"{all_desc.shape[0]} ORB descriptors; codec and BoW use every 5th frame as a keyframe "
        f"({len(kfs)} keyframes). One thread. Command: "
        "`.venv/bin/python benchmarks/bench_vocabulary.py`.",
        "",
        "| k | L | words | file MB | train s | lookup desc/s | mean Hamming to word | "
        "KF intra bits/feat: word | residual | total | BoW score consecutive KFs | "
        "BoW score vs unrelated photos |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k, depth, voc, size, t_train, rate, ham, near, unrelated, bits in rows:
        lines.append(
            f"| {k} | {depth} | {voc.n_words} | {size / 1e6:.2f} | {t_train:.0f} | {rate:,.0f} | "
            f"{ham:.1f} | {bits.get('word', 0):.1f} | {bits.get('residual', 0):.1f} | "
            f"**{bits['total']:.1f}** | {near:.3f} | {unrelated:.3f} |"
        )
    best = min(rows, key=lambda r: r[9]["total"])
    default_row = next(r for r in rows if (r[0], r[1]) == (DEFAULT_K, DEFAULT_DEPTH))
    ratio = {(r[0], r[1]): r[7] / max(r[8], 1e-9) for r in rows}
    lines += [
        "",
        "Lookup target ≥ 50,000 descriptors/s: "
        + ("met by every configuration." if min(r[5] for r in rows) >= 5e4 else "NOT met by all.")
        + f" Lowest codec cost: k={best[0]}, L={best[1]} ({best[9]['total']:.1f} bits/feature).",
        "",
        f"Choice for the default (`common/assets/orb_vocabulary.npz`): **k={DEFAULT_K}, "
        f"L={DEFAULT_DEPTH}** ({default_row[2].n_words} words, {default_row[3] / 1e6:.2f} MB): "
        f"{default_row[9]['total']:.1f} bits/feature, "
        f"{default_row[9]['total'] - best[9]['total']:.1f} above the cheapest row. With the "
        "codec's context model the XOR residual is nearly independent of the tree (the "
        "residual column), and each level adds ~log2(k) bits of word index, so the codec "
        "cost is nearly flat in k and L. The choice is then made for place recognition in "
        "the cloud: the ratio of the BoW score between consecutive keyframes to the score "
        "against unrelated photographs is "
        + ", ".join(f"{r:.0f}x (k={k}, L={d})" for (k, d), r in ratio.items())
        + "; the default takes most of that discrimination at a ~1 bit/feature premium over "
        "k=10, L=4, a lookup rate far above the target and a file under 5 MB. The tree "
        "trained here with the default's settings is "
        + (
            "bit-identical to"
            if default_row[2].fingerprint() == Vocabulary.load().fingerprint()
            else "NOT identical to"
        )
        + " the committed default.",
    ]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
