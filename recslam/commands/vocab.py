"""``recslam vocab train``: train the ORB vocabulary tree over image folders or datasets.

Sources may be image folders (``*.png``, ``*.jpg``, searched recursively), EuRoC-layout
datasets (``mav0/cam*/data``) or the keyword ``skimage`` (scikit-image's bundled photographs
at several scales, rotations and blurs — how the default vocabulary in ``common/assets`` was
trained; independent of every test sequence).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _train(args: argparse.Namespace) -> int:
    from common.vocabulary import Vocabulary, VocabularyTrainingConfig
    from common.vocabulary_training import collect_descriptors

    descs, what = collect_descriptors(args.images, args.stride)
    n = sum(d.shape[0] for d in descs)
    print(f"training on {n} descriptors from {len(descs)} images: {what}")
    cfg = VocabularyTrainingConfig(
        k=args.k, depth=args.depth, seed=args.seed, bit_context_parents=args.context_parents
    )
    voc = Vocabulary.train(descs, cfg, trained_on=f"ORB(1000, 1.2, 8) on {what}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    voc.save(out)
    print(
        f"wrote {out}: k={voc.k} depth={voc.depth} words={voc.n_words} "
        f"nodes={voc.node_desc.shape[0]} size={out.stat().st_size / 1e6:.2f} MB"
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("vocab", help="visual vocabulary (ORB k-majority tree)")
    sub = p.add_subparsers(dest="vocab_command", metavar="ACTION", required=True)
    t = sub.add_parser("train", help="train a vocabulary over image folders or datasets")
    t.add_argument(
        "--images",
        nargs="+",
        required=True,
        metavar="DIR_OR_DATASET",
        help="image folders, EuRoC-layout datasets, or 'skimage' (bundled photographs)",
    )
    t.add_argument("--k", type=int, default=10, help="branching factor (default 10)")
    t.add_argument("--depth", type=int, default=5, help="tree depth L (default 5)")
    t.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    t.add_argument(
        "--context-parents",
        type=int,
        default=10,
        help="parents per descriptor bit in the codec's context model (default 10)",
    )
    t.add_argument("--stride", type=int, default=1, help="use every n-th image of folders")
    t.add_argument("--out", required=True, help="output .npz file")
    t.set_defaults(func=_train)
