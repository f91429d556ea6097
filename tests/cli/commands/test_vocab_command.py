"""``recslam vocab train`` over an image folder and an EuRoC-layout dataset."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import pytest
import skimage.data

from common.vocabulary import Vocabulary, VocabularyError
from recslam.commands import vocab


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    vocab.register(parser.add_subparsers())
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture()
def sources(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    dataset = tmp_path / "seq" / "mav0" / "cam0" / "data"
    dataset.mkdir(parents=True)
    for i, name in enumerate(("camera", "coins", "brick")):
        img = np.asarray(getattr(skimage.data, name)(), dtype=np.uint8)
        cv2.imwrite(str(folder / f"{name}.png"), img)
        cv2.imwrite(str(dataset / f"{i:03d}.png"), img[::-1])
    return folder, tmp_path / "seq"


def test_train_over_folder_and_dataset(sources, tmp_path, capsys):
    folder, dataset = sources
    out = tmp_path / "voc.npz"
    argv = [
        "vocab",
        "train",
        "--images",
        str(folder),
        str(dataset),
        "--k",
        "3",
        "--depth",
        "2",
        "--context-parents",
        "2",
        "--out",
        str(out),
    ]
    assert run(argv) == 0
    voc = Vocabulary.load(out)
    assert (voc.k, voc.depth) == (3, 2)
    assert voc.meta["n_images"] == 6
    assert voc.bit_parents.shape == (256, 2)
    assert "photos" in voc.meta["trained_on"] and "seq" in voc.meta["trained_on"]
    assert "words=" in capsys.readouterr().out


def test_missing_source_is_named(tmp_path):
    with pytest.raises(VocabularyError, match="nowhere"):
        run(["vocab", "train", "--images", str(tmp_path / "nowhere"), "--out", "x.npz"])
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(VocabularyError, match="no images"):
        run(["vocab", "train", "--images", str(empty), "--out", "x.npz"])
