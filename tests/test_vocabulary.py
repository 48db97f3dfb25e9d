"""jsve.frontend._vocabulary: the DBoW2 text vocabulary for ORB-SLAM3.

Oracles: hand-made descriptor sets whose clusters, centres and IDF weights are known; a plain-Python
descent of the tree; and DBoW2 itself (ORB-SLAM3 v1.0's Thirdparty/DBoW2, compiled on the fly when its
sources, g++ and OpenCV's headers are there), which must load the file and put descriptors in the same
words.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from jsve.frontend import _vocabulary as voc

DBOW2_SOURCES = Path(os.environ.get("JSVE_DBOW2_DIR", "/work/cache/src/ORB_SLAM3/Thirdparty/DBoW2"))


def _flip_bits(rng: np.random.Generator, proto: np.ndarray, n: int, n_bits: int) -> np.ndarray:
    """n copies of a packed descriptor with n_bits random bits flipped in each."""
    bits = np.repeat(np.unpackbits(proto)[None], n, axis=0)
    for row in bits:
        row[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def _clustered(seed: int = 0, n_protos: int = 3, per_proto: int = 40, n_bits: int = 6):
    """Descriptors around n_protos far-apart prototypes (a few flipped bits each), and the prototypes."""
    rng = np.random.default_rng(seed)
    protos = rng.integers(0, 256, (n_protos, 32), dtype=np.uint8)
    groups = [_flip_bits(rng, p, per_proto, n_bits) for p in protos]
    return protos, groups


def _random_images(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Per image 300 random descriptors (plenty of distinct values for a deep tree)."""
    return [rng.integers(0, 256, (300, 32), dtype=np.uint8) for _ in range(n)]


def test_clusters_are_found_with_majority_centres():
    # Three prototypes 128 bits apart on average, members 6 bits off: k-medians with k = 3 at one level must
    # give one word per prototype, and the majority vote of the members is the prototype itself (each bit is
    # flipped in at most a few of 40 members).
    protos, groups = _clustered()
    vocab = voc.build_vocabulary(descriptors=[np.concatenate(groups)], k=3, levels=1)
    assert vocab.n_nodes == 3 and vocab.is_leaf.all() and (vocab.parent == 0).all()
    found = {bytes(d) for d in vocab.descriptor}
    assert found == {bytes(p) for p in protos}


def test_idf_weights_count_images():
    # Image 0 holds all three groups, images 1-3 only group 0: N = 4 images; the word of group 0 is in
    # all 4 (ln 1 = 0), the others in 1 (ln 4). Exact copies within a group: k-means++ draws in proportion
    # to the distance, so no second centre can fall in a group that has one, and the clusters are the groups.
    protos, groups = _clustered(seed=1, n_bits=0)
    images = [np.concatenate(groups), groups[0][:5], groups[0][5:10], groups[0][10:15]]
    vocab = voc.build_vocabulary(descriptors=images, k=3, levels=1)
    weight = {bytes(d): w for d, w in zip(vocab.descriptor, vocab.weight, strict=True)}
    assert weight[bytes(protos[0])] == 0.0
    assert weight[bytes(protos[1])] == pytest.approx(math.log(4)) == weight[bytes(protos[2])]


def test_small_nodes_get_one_child_per_descriptor_and_singletons_stay_leaves():
    # DBoW2's HKmeansStep: at most k descriptors -> one child each; a child of one descriptor is not split
    # further, so with 4 distinct descriptors and k = 10 the tree is 4 leaves under the root at any depth.
    rng = np.random.default_rng(2)
    d = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    vocab = voc.build_vocabulary(descriptors=[d], k=10, levels=6)
    assert vocab.n_nodes == 4 and vocab.is_leaf.all()
    np.testing.assert_array_equal(vocab.descriptor, d)


def test_deterministic_under_the_seed():
    rng = np.random.default_rng(3)
    images = _random_images(rng, 6)
    a = voc.vocabulary_text(voc.build_vocabulary(descriptors=images, k=5, levels=3, seed=7))
    b = voc.vocabulary_text(voc.build_vocabulary(descriptors=images, k=5, levels=3, seed=7))
    c = voc.vocabulary_text(voc.build_vocabulary(descriptors=images, k=5, levels=3, seed=8))
    assert a == b
    assert a != c  # the seed reaches the k-means++ draws


def _descend(vocab: voc.Vocabulary, d: np.ndarray) -> int:
    """Plain-Python DBoW2 transform: nearest child by Hamming distance, first in file order on ties."""
    children: dict[int, list[int]] = {}
    for node, parent in enumerate(vocab.parent, 1):
        children.setdefault(int(parent), []).append(node)
    node = 0
    while node in children:
        dists = [int(np.unpackbits(d ^ vocab.descriptor[c - 1]).sum()) for c in children[node]]
        node = children[node][int(np.argmin(dists))]
    return node


def test_format_round_trip_and_tree_shape(tmp_path):
    rng = np.random.default_rng(4)
    images = _random_images(rng, 5)
    vocab = voc.build_vocabulary(descriptors=images, k=4, levels=4)
    path = voc.write_vocabulary(vocab, tmp_path / "voc.txt")
    text = path.read_text()
    assert text.splitlines()[0] == "4 4 0 0"  # k L L1_NORM TF_IDF
    assert not text.endswith("\n")  # DBoW2's loader would read an empty last line as a node
    assert len(text.splitlines()) == vocab.n_nodes + 1
    back = voc.read_vocabulary(path)
    for name in ("parent", "descriptor", "is_leaf"):
        np.testing.assert_array_equal(getattr(back, name), getattr(vocab, name))
    np.testing.assert_array_equal(back.weight, vocab.weight)  # repr() round-trips doubles exactly
    ids = np.arange(1, vocab.n_nodes + 1)
    assert (vocab.parent < ids).all()  # parents first
    depth = np.zeros(vocab.n_nodes + 1, int)
    for node, parent in zip(ids, vocab.parent, strict=True):
        depth[node] = depth[parent] + 1
    assert depth.max() <= vocab.levels
    assert (np.bincount(vocab.parent) <= vocab.k).all()
    # Leaves are exactly the nodes nobody points to; words carry the IDF, inner nodes 0.
    assert (
        not np.isin(ids[vocab.is_leaf], vocab.parent).any()
        and np.isin(ids[~vocab.is_leaf], vocab.parent).all()
    )
    assert (vocab.weight[~vocab.is_leaf] == 0).all()
    assert (vocab.weight[vocab.is_leaf] > 0).any() and (vocab.weight >= 0).all()
    assert vocab.weight.max() <= math.log(len(images))
    # The vectorised descent equals the plain-Python one.
    sample = np.concatenate(images)[::37]
    np.testing.assert_array_equal(voc.words_of(vocab, sample), [_descend(vocab, d) for d in sample])


def test_read_rejects_what_dbow2_would_misread(tmp_path):
    good = "2 1 0 0\n0 1 " + " ".join(["0"] * 32) + " 0.5"
    (tmp_path / "ok.txt").write_text(good)
    assert voc.read_vocabulary(tmp_path / "ok.txt").n_words == 1
    (tmp_path / "trailing.txt").write_text(good + "\n\n")
    with pytest.raises(voc.VocabularyFormatError, match="trailing.txt:3: .*empty line"):
        voc.read_vocabulary(tmp_path / "trailing.txt")
    (tmp_path / "order.txt").write_text("2 1 0 0\n2 1 " + " ".join(["0"] * 32) + " 0.5")
    with pytest.raises(voc.VocabularyFormatError, match="order.txt:2: parent 2 does not come before node 1"):
        voc.read_vocabulary(tmp_path / "order.txt")
    (tmp_path / "k.txt").write_text("21 1 0 0\n")
    with pytest.raises(voc.VocabularyFormatError, match="k.txt:1"):
        voc.read_vocabulary(tmp_path / "k.txt")


def test_arguments_are_checked():
    with pytest.raises(ValueError, match="k must be in 2..20"):
        voc.build_vocabulary(descriptors=[np.zeros((3, 32), np.uint8)], k=21)
    with pytest.raises(ValueError, match="levels must be in 1..10"):
        voc.build_vocabulary(descriptors=[np.zeros((3, 32), np.uint8)], levels=0)
    with pytest.raises(ValueError, match="no training descriptors"):
        voc.build_vocabulary(descriptors=[np.zeros((0, 32), np.uint8)])


def test_command_line_on_images(tmp_path):
    # Textured images (smoothed noise has plenty of FAST corners) through the options the lead mounts as
    # `jsve frontend vocabulary`.
    rng = np.random.default_rng(5)
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        noise = cv2.GaussianBlur(rng.integers(0, 256, (240, 320)).astype(np.float32), (0, 0), 1.5)
        cv2.imwrite(str(folder / f"{i}.png"), (255 * (noise - noise.min()) / np.ptp(noise)).astype(np.uint8))
    parser = argparse.ArgumentParser()
    voc.add_vocabulary_arguments(parser)
    out = tmp_path / "voc.txt"
    args = parser.parse_args([str(folder), "-o", str(out), "--k", "5", "--levels", "3", "--no-progress"])
    assert voc.run_vocabulary(args) == 0
    vocab = voc.read_vocabulary(out)
    assert vocab.k == 5 and vocab.levels == 3 and vocab.n_words > 100
    missing = parser.parse_args([str(tmp_path / "nothing"), "-o", str(out)])
    assert voc.run_vocabulary(missing) == 2


_LOADER = r"""
// Loads a DBoW2 text vocabulary as ORB-SLAM3 does (ORBVocabulary::loadFromTextFile), prints its size and
// codes, then the word id and weight of each 32-byte descriptor read from stdin.
#include <iostream>
#include <vector>
#include "DBoW2/FORB.h"
#include "DBoW2/TemplatedVocabulary.h"
typedef DBoW2::TemplatedVocabulary<DBoW2::FORB::TDescriptor, DBoW2::FORB> ORBVocabulary;
int main(int argc, char** argv) {
  ORBVocabulary voc;
  if (argc < 2 || !voc.loadFromTextFile(argv[1])) { std::cout << "failed" << std::endl; return 1; }
  std::cout << voc.size() << " " << voc.getBranchingFactor() << " " << voc.getDepthLevels() << " "
            << voc.getScoringType() << " " << voc.getWeightingType() << std::endl;
  std::cout.precision(17);
  std::vector<int> bytes;
  int value;
  while (std::cin >> value) {
    bytes.push_back(value);
    if (bytes.size() == 32) {
      cv::Mat d(1, 32, CV_8U);
      for (int i = 0; i < 32; ++i) d.at<unsigned char>(0, i) = (unsigned char)bytes[i];
      const DBoW2::WordId id = voc.transform(d);
      std::cout << id << " " << voc.getWordWeight(id) << std::endl;
      bytes.clear();
    }
  }
  return 0;
}
"""


@pytest.fixture(scope="module")
def dbow2_loader(tmp_path_factory):
    """ORB-SLAM3's DBoW2 compiled with a tiny loader program; skipped where it cannot be built."""
    gxx = shutil.which("g++")
    names = ("FORB", "BowVector", "FeatureVector", "ScoringObject")
    sources = [DBOW2_SOURCES / f"DBoW2/{n}.cpp" for n in names]
    sources += [DBOW2_SOURCES / f"DUtils/{n}.cpp" for n in ("Random", "Timestamp")]
    if gxx is None or not all(p.is_file() for p in sources):
        pytest.skip(f"g++ or ORB-SLAM3's DBoW2 sources ({DBOW2_SOURCES}, JSVE_DBOW2_DIR) missing")
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "opencv4"], capture_output=True, text=True)
    if flags.returncode != 0:
        pytest.skip("OpenCV's development files (pkg-config opencv4) missing")
    folder = tmp_path_factory.mktemp("dbow2")
    (folder / "load.cc").write_text(_LOADER)
    exe = folder / "load"
    build = subprocess.run(
        [gxx, "-std=c++17", "-O1", "-w", f"-I{DBOW2_SOURCES}", str(folder / "load.cc"), *map(str, sources),
         *flags.stdout.split(), "-o", str(exe)],
        capture_output=True, text=True,
    )  # fmt: skip
    if build.returncode != 0:
        pytest.skip(f"DBoW2 loader did not compile: {build.stderr[-500:]}")
    return exe


def test_dbow2_loads_it_and_agrees_on_words(tmp_path, dbow2_loader):
    rng = np.random.default_rng(6)
    images = _random_images(rng, 8)
    vocab = voc.build_vocabulary(descriptors=images, k=10, levels=6)
    path = voc.write_vocabulary(vocab, tmp_path / "voc.txt")
    queries = np.concatenate([np.concatenate(images)[::11], rng.integers(0, 256, (50, 32), dtype=np.uint8)])
    out = subprocess.run(
        [str(dbow2_loader), str(path)],
        input=" ".join(map(str, queries.ravel())),
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].split() == [
        str(vocab.n_words),
        "10",
        "6",
        "0",
        "0",
    ]  # no phantom node from the file's end
    ids = np.array([int(line.split()[0]) for line in lines[1:]])
    weights = np.array([float(line.split()[1]) for line in lines[1:]])
    node = voc.words_of(vocab, queries)
    np.testing.assert_array_equal(ids, np.cumsum(vocab.is_leaf)[node - 1] - 1)  # word id: rank among leaves
    np.testing.assert_allclose(weights, vocab.weight[node - 1], rtol=1e-15)  # 17 digits printed, read exactly
