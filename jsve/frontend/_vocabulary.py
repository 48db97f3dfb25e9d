"""A DBoW2 vocabulary for ORB-SLAM3, trained on a user's images: `jsve frontend vocabulary IMAGES -o voc.txt`.

ORB-SLAM3 loads its bag-of-words vocabulary with DBoW2's `TemplatedVocabulary::loadFromTextFile`
(ORBvoc.txt). The real ORBvoc.txt is not always at hand; any vocabulary in the same text format works, and
monocular initialisation does not use it (relocalisation, loop closing and map merging do).

    build_vocabulary(images)      ORB descriptors (ORB-SLAM3's settings) -> hierarchical binary k-medians
                                  tree with IDF weights on the leaves (TF-IDF, L1 scoring)
    write_vocabulary / read_vocabulary   the DBoW2 text format
    words_of(vocab, descriptors)  the word of each descriptor, descending the tree as DBoW2's transform does

The text format, from DBoW2 as ORB-SLAM3 v1.0 ships it (Thirdparty/DBoW2/DBoW2/TemplatedVocabulary.h,
loadFromTextFile and saveToTextFile; FORB.cpp; BowVector.h):

- line 1: `k L scoring weighting`; the loader accepts 0 <= k <= 20, 1 <= L <= 10, scoring 0..5
  (L1_NORM, L2_NORM, CHI_SQUARE, KL, BHATTACHARYYA, DOT_PRODUCT) and weighting 0..3 (TF_IDF, TF, IDF,
  BINARY). ORBvoc.txt and this module: `10 6 0 0` (TF-IDF, L1).
- then one line per node except the root, `parent is_leaf d_0 ... d_31 weight`: the node's id is its line
  number (the root is 0, the first node line is 1), so a parent must come before its children; a node's
  children are listed in file order, which is the order DBoW2 compares them in. The 32 descriptor bytes
  are decimal. `weight` is read for every node but only a leaf's is used: its IDF, ln(N / N_i), N the
  number of training images and N_i the number of them with a feature in that word; inner nodes carry 0.
- the loader reads lines until end of file and turns even an empty last line into a node (a child of the
  root with an undefined descriptor), so the file must not end with a newline.

The tree is built as DBoW2's `create` builds it (HKmeansStep): at each node with more than k
descriptors, k-means++ seeding (DBoW2's variant: a new centre is drawn with probability proportional to
its Hamming distance to the nearest centre, not its square; seeding stops early where every descriptor
already coincides with a centre), then Lloyd iterations with Hamming assignment (ties to the lower
cluster) and majority-vote centres (FORB::meanValue: a bit is set when at least half the members have
it), until no assignment changes. A node with at most k descriptors gets one child per descriptor; a child
with more than one descriptor is split further until level L. Two deliberate differences: this module
splits all nodes of one level together (vectorised over nodes, in numpy), writes nodes level by level
(DBoW2 writes them depth first; both put parents first), and drops a cluster that ends empty (DBoW2
would keep it as a word no feature reaches). The IDF counts each training descriptor in the word that
descending the tree gives it (DBoW2's setNodeWeights uses `transform`, not the clustering's groups).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

DESCRIPTOR_BYTES = 32
"""ORB descriptors: 256 bits (FORB::L)."""

SCORING_L1 = 0
"""DBoW2 ScoringType L1_NORM, ORB-SLAM3's (ORBvoc.txt line 1)."""

WEIGHTING_TF_IDF = 0
"""DBoW2 WeightingType TF_IDF, ORB-SLAM3's."""

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")

_MAX_ITERATIONS = 200


class VocabularyFormatError(ValueError):
    """A vocabulary text file that DBoW2's loader would refuse or misread; names the file and line."""


@dataclass(frozen=True)
class Vocabulary:
    """A DBoW2 vocabulary tree. Node i + 1 is row i of the arrays; the root (node 0) is implicit.

    Attributes:
        k: branching factor. levels: depth L.
        parent: [M] int64 parent node id of each node (0: the root), always lower than the node's id.
        descriptor: [M, 32] uint8 ORB descriptor (a cluster centre) of each node.
        is_leaf: [M] bool, the words.
        weight: [M] float64 IDF weight ln(N / N_i) of each word (0 for inner nodes, and for a word no
            training image reaches).
        scoring, weighting: DBoW2's codes (SCORING_L1, WEIGHTING_TF_IDF).
        n_images: training images N; n_descriptors: training descriptors.
    """

    k: int
    levels: int
    parent: np.ndarray
    descriptor: np.ndarray
    is_leaf: np.ndarray
    weight: np.ndarray
    scoring: int = SCORING_L1
    weighting: int = WEIGHTING_TF_IDF
    n_images: int = 0
    n_descriptors: int = 0

    @property
    def n_nodes(self) -> int:
        """Nodes without the root (the file's node lines)."""
        return len(self.parent)

    @property
    def n_words(self) -> int:
        return int(np.count_nonzero(self.is_leaf))


# --------------------------------------------------------------------------------------------------
# Hamming geometry of packed descriptors


def _hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between packed descriptors, broadcasting over leading axes: [..., 32] -> [...]."""
    # Viewed as four 64-bit words: a quarter of the elements to XOR and count.
    a64 = np.ascontiguousarray(a).view(np.uint64)
    b64 = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(np.bitwise_xor(a64, b64)).sum(axis=-1, dtype=np.int64)


def _seed_centres(
    desc: np.ndarray, seg: np.ndarray, starts: np.ndarray, sizes: np.ndarray, k: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """k-means++ seeding in every segment at once, DBoW2's initiateClustersKMpp.

    Arguments:
        desc: [N, 32] descriptors, grouped by segment (contiguous). seg: [N] segment of each.
        starts, sizes: [S] first row and row count of each segment (all sizes > k).
    Returns:
        (centres [S, k, 32] uint8, valid [S, k] bool); a segment whose descriptors all coincide with a
        centre gets fewer than k.
    """
    n_seg = len(starts)
    centres = np.zeros((n_seg, k, DESCRIPTOR_BYTES), np.uint8)
    valid = np.zeros((n_seg, k), bool)
    first = starts + np.floor(rng.random(n_seg) * sizes).astype(np.int64)
    centres[:, 0] = desc[first]
    valid[:, 0] = True
    nearest = _hamming(desc, centres[seg, 0])
    for j in range(1, k):
        # Draw r uniformly in 1..total and take the first descriptor whose running sum of distances reaches
        # r: probability proportional to the distance, DBoW2's cut_d in (0, dist_sum].
        running = np.cumsum(nearest)
        before = np.where(starts > 0, running[starts - 1], 0)
        total = running[starts + sizes - 1] - before
        live = total > 0
        r = np.floor(rng.random(n_seg) * np.maximum(total, 1)).astype(np.int64) + 1
        pick = np.searchsorted(running, before + r, side="left")
        pick = np.minimum(pick, starts + sizes - 1)
        centres[live, j] = desc[pick[live]]
        valid[:, j] = live & valid[:, j - 1]
        update = valid[seg, j]
        nearest = np.where(update, np.minimum(nearest, _hamming(desc, centres[seg, j])), nearest)
    return centres, valid


_BYTE_BITS = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).astype(np.float64)
"""[256, 8] the bits of every byte value, most significant first (np.packbits' order, FORB's)."""


def _majority(desc: np.ndarray, cluster: np.ndarray, n_clusters: int) -> tuple[np.ndarray, np.ndarray]:
    """Majority-vote centre of every cluster (FORB::meanValue): ([C, 32] uint8, member counts [C])."""
    counts = np.bincount(cluster, minlength=n_clusters)
    if n_clusters <= 1024:
        # Few clusters: a histogram of byte values per (cluster, byte), then its bits (a float product,
        # exact for counts below 2^53, so BLAS does it).
        bit_sums = np.concatenate(
            [
                np.bincount(cluster * 256 + desc[:, j], minlength=n_clusters * 256).reshape(-1, 256)
                @ _BYTE_BITS
                for j in range(DESCRIPTOR_BYTES)
            ],
            axis=1,
        ).astype(np.int64)
    else:
        order = np.argsort(cluster, kind="stable")
        present = np.flatnonzero(counts)
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        bits = np.unpackbits(desc[order].T, axis=0)  # [256, N]: reduceat along contiguous rows
        bit_sums = np.zeros((n_clusters, DESCRIPTOR_BYTES * 8), np.int64)
        bit_sums[present] = np.add.reduceat(bits, offsets[present], axis=1, dtype=np.int64).T
    # A bit is set where at least ceil(n / 2) members have it (FORB::meanValue's N2).
    centre = np.packbits((2 * bit_sums >= counts[:, None]).astype(np.uint8), axis=1)
    return centre, counts


def _kmedians(
    desc: np.ndarray, seg: np.ndarray, starts: np.ndarray, sizes: np.ndarray, k: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Binary k-medians in every segment at once (DBoW2's HKmeansStep for segments of more than k).

    Returns:
        (cluster [N] in 0..k-1 per descriptor, centres [S, k, 32]).
    """
    n_seg = len(starts)
    centres, valid = _seed_centres(desc, seg, starts, sizes, k, rng)
    far = np.int64(DESCRIPTOR_BYTES * 8 + 1)

    def assign(centres: np.ndarray) -> np.ndarray:
        dist = np.where(valid[seg], _hamming(desc[:, None, :], centres[seg]), far)
        return np.argmin(dist, axis=1)  # the first minimum: DBoW2's strict '<' keeps the lower cluster

    cluster = assign(centres)
    for _ in range(_MAX_ITERATIONS):
        flat, members = _majority(desc, seg * k + cluster, n_seg * k)
        # An emptied cluster keeps its centre (DBoW2's meanValue of nothing is undefined); dropped later.
        centres = np.where((members > 0).reshape(n_seg, k, 1), flat.reshape(n_seg, k, -1), centres)
        previous, cluster = cluster, assign(centres)
        if np.array_equal(cluster, previous):
            break
    else:
        logger.warning("k-medians stopped after %d iterations without converging", _MAX_ITERATIONS)
    return cluster, centres


# --------------------------------------------------------------------------------------------------
# The tree


def _children_table(vocab: Vocabulary) -> np.ndarray:
    """[M + 1, k] child node ids of every node (root first), in file order, -1 where there are fewer."""
    table = np.full((vocab.n_nodes + 1, max(vocab.k, 1)), -1, np.int64)
    ids = np.arange(1, vocab.n_nodes + 1)
    order = np.argsort(vocab.parent, kind="stable")
    parents = vocab.parent[order]
    first = np.searchsorted(parents, parents, side="left")
    slot = np.arange(len(parents)) - first
    if len(slot) and slot.max() >= table.shape[1]:
        raise ValueError(f"a node has {slot.max() + 1} children, more than k = {vocab.k}")
    table[parents, slot] = ids[order]
    return table


def words_of(vocab: Vocabulary, descriptors: np.ndarray) -> np.ndarray:
    """The node id of the word each descriptor falls in, descending as DBoW2's transform does.

    At every level the nearest child in Hamming distance is taken, the first in file order on ties, until a
    leaf is reached.

    Arguments:
        vocab: the tree. descriptors: [N, 32] uint8 ORB descriptors.
    Returns:
        [N] int64 node ids (1..M) of leaves; the word index DBoW2 reports is the leaf's rank among the
        leaves in file order (np.cumsum(vocab.is_leaf)[node - 1] - 1).
    """
    descriptors = np.ascontiguousarray(descriptors, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
    children = _children_table(vocab)
    node_desc = np.concatenate([np.zeros((1, DESCRIPTOR_BYTES), np.uint8), vocab.descriptor])
    leaf = np.concatenate([[False], vocab.is_leaf])
    node = np.zeros(len(descriptors), np.int64)
    far = np.int64(DESCRIPTOR_BYTES * 8 + 1)
    for _ in range(vocab.levels + 1):
        active = np.flatnonzero(~leaf[node])
        if active.size == 0:
            break
        cand = children[node[active]]
        dist = np.where(
            cand >= 0, _hamming(descriptors[active, None, :], node_desc[np.maximum(cand, 0)]), far
        )
        node[active] = cand[np.arange(len(active)), np.argmin(dist, axis=1)]
    return node


def build_vocabulary(
    image_paths: Sequence[str | os.PathLike] | None = None,
    *,
    descriptors: Sequence[np.ndarray] | None = None,
    k: int = 10,
    levels: int = 6,
    n_features: int = 1000,
    seed: int = 0,
    progress: bool = False,
) -> Vocabulary:
    """Train a DBoW2 vocabulary (TF-IDF, L1) on ORB descriptors of images, deterministically under `seed`.

    Arguments:
        image_paths: images (8-bit, read as grey); their ORB features are extracted with ORB-SLAM3's
            settings (jsve.image.extract_orb, OrbSettings with n_features). Or:
        descriptors: one [n_i, 32] uint8 array per training image, instead of image_paths.
        k: branching factor (ORBvoc.txt: 10; DBoW2 loads at most 20). levels: depth L (ORBvoc.txt: 6;
            at most 10). ORB-SLAM3 groups features by their node 4 levels above the words (ComputeBoW),
            so L = 6 keeps its grouping at level 2 as with ORBvoc.txt.
        n_features: ORB features per image (ORBextractor.nFeatures).
        seed: seeds the k-means++ draws.
        progress: show a progress bar over the images.
    Returns:
        The Vocabulary; write it with write_vocabulary.
    """
    if not 2 <= k <= 20:
        raise ValueError(f"k must be in 2..20 (DBoW2's loader refuses k > 20); got {k}")
    if not 1 <= levels <= 10:
        raise ValueError(f"levels must be in 1..10 (DBoW2's loader refuses L > 10); got {levels}")
    if (image_paths is None) == (descriptors is None):
        raise ValueError("give exactly one of image_paths and descriptors")
    if descriptors is None:
        assert image_paths is not None
        descriptors = _image_descriptors(image_paths, n_features, progress)
    per_image = [np.ascontiguousarray(d, np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in descriptors]
    n_images = len(per_image)
    if n_images == 0 or sum(len(d) for d in per_image) == 0:
        raise ValueError("no training descriptors (no images, or no ORB features in them)")
    doc = np.concatenate([np.full(len(d), i, np.int64) for i, d in enumerate(per_image)])
    desc = np.concatenate(per_image)
    rng = np.random.default_rng(seed)

    parent: list[np.ndarray] = []
    node_desc: list[np.ndarray] = []
    n_nodes = 0
    # Descriptors still to split, grouped by the node they belong to (contiguous), and that node's id.
    owner = np.zeros(len(desc), np.int64)
    rows = np.arange(len(desc))
    for _level in range(1, levels + 1):
        if rows.size == 0:
            break
        order = np.argsort(owner, kind="stable")
        rows, owner = rows[order], owner[order]
        nodes, starts, sizes = np.unique(owner, return_index=True, return_counts=True)
        seg = np.repeat(np.arange(len(nodes)), sizes)
        slot = np.arange(len(rows)) - starts[seg]  # a node of at most k: one child per descriptor
        big = np.flatnonzero(sizes > k)
        local = np.full(len(nodes), -1, np.int64)
        local[big] = np.arange(len(big))
        in_big = local[seg] >= 0
        centres = np.zeros((len(big), k, DESCRIPTOR_BYTES), np.uint8)
        if big.size:
            big_starts = np.concatenate([[0], np.cumsum(sizes[big])[:-1]])
            slot[in_big], centres = _kmedians(
                desc[rows[in_big]], local[seg[in_big]], big_starts, sizes[big], k, rng
            )
        # Children: every (node, slot) with members, ordered by node, then slot.
        key = seg * k + slot
        keys, first, count = np.unique(key, return_index=True, return_counts=True)
        key_seg, key_slot = keys // k, keys % k
        child_desc = desc[rows[first]]
        from_kmeans = local[key_seg] >= 0
        child_desc[from_kmeans] = centres[local[key_seg[from_kmeans]], key_slot[from_kmeans]]
        parent.append(nodes[key_seg])
        node_desc.append(child_desc)
        child = np.searchsorted(keys, key)
        child_ids = n_nodes + 1 + np.arange(len(keys))
        n_nodes += len(keys)
        # Rows go on with their child; a child of one descriptor stays a leaf (DBoW2 splits only > 1).
        keep = count[child] > 1
        rows, owner = rows[keep], child_ids[child[keep]]

    parent_arr = np.concatenate(parent)
    is_leaf = np.ones(n_nodes, bool)
    is_leaf[parent_arr[parent_arr > 0] - 1] = False
    vocab = Vocabulary(
        k=k,
        levels=levels,
        parent=parent_arr,
        descriptor=np.concatenate(node_desc),
        is_leaf=is_leaf,
        weight=np.zeros(n_nodes),
        n_images=n_images,
        n_descriptors=len(desc),
    )
    return _with_idf(vocab, desc, doc)


def _with_idf(vocab: Vocabulary, desc: np.ndarray, doc: np.ndarray) -> Vocabulary:
    """IDF on the words, DBoW2's setNodeWeights: ln(N / N_i), N_i the images with a feature in word i."""
    word = words_of(vocab, desc)
    pairs = np.unique(word * (vocab.n_images + 1) + doc)
    n_i = np.bincount(pairs // (vocab.n_images + 1), minlength=vocab.n_nodes + 1)[1:]
    weight = np.where(
        vocab.is_leaf & (n_i > 0), np.log(vocab.n_images / np.maximum(n_i, 1), dtype=np.float64), 0.0
    )
    return Vocabulary(**{**vocab.__dict__, "weight": weight})


def _image_descriptors(
    paths: Sequence[str | os.PathLike], n_features: int, progress: bool
) -> list[np.ndarray]:
    import cv2
    from tqdm import tqdm

    from jsve.image import OrbSettings, extract_orb

    settings = OrbSettings(n_features=n_features)
    out = []
    for path in tqdm(paths, desc="ORB", unit="image", disable=not progress):
        image = cv2.imread(os.fspath(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileNotFoundError(f"{path}: not a readable image")
        out.append(extract_orb(image, settings).descriptors)
    return out


# --------------------------------------------------------------------------------------------------
# Text format


def _format_weight(w: float) -> str:
    return repr(float(w)) if w != 0 else "0"


def vocabulary_text(vocab: Vocabulary) -> str:
    """The DBoW2 text file of a vocabulary (module docstring: the format), without a final newline."""
    header = f"{vocab.k} {vocab.levels} {vocab.scoring} {vocab.weighting}"
    lines = [header]
    for p, leaf, d, w in zip(vocab.parent, vocab.is_leaf, vocab.descriptor, vocab.weight, strict=True):
        lines.append(f"{int(p)} {int(leaf)} {' '.join(map(str, d.tolist()))} {_format_weight(w)}")
    return "\n".join(lines)


def write_vocabulary(vocab: Vocabulary, path: str | os.PathLike) -> Path:
    """Write the DBoW2 text vocabulary atomically (under `<path>.partial`, renamed when complete).

    The file has no final newline: DBoW2's loader would read an empty last line as one more node.
    """
    from jsve.io import write_text

    return write_text(path, vocabulary_text(vocab))


def read_vocabulary(path: str | os.PathLike) -> Vocabulary:
    """Read a DBoW2 text vocabulary (ORBvoc.txt or write_vocabulary's), checking what the loader assumes.

    Raises:
        VocabularyFormatError naming the file and line: a bad header, a parent that does not come before
        its child, a node line without 32 bytes and a weight, more than k children.
    """
    path = Path(path)
    with open(path) as f:
        header = f.readline().split()
        if len(header) != 4:
            raise VocabularyFormatError(f"{path}:1: expected 'k L scoring weighting', got {header}")
        k, levels, scoring, weighting = (int(v) for v in header)
        if not (0 <= k <= 20 and 1 <= levels <= 10 and 0 <= scoring <= 5 and 0 <= weighting <= 3):
            raise VocabularyFormatError(f"{path}:1: values DBoW2's loader refuses: {header}")
        parent, leaf, desc, weight = [], [], [], []
        for line_no, line in enumerate(f, 2):
            fields = line.split()
            if len(fields) != DESCRIPTOR_BYTES + 3:
                raise VocabularyFormatError(
                    f"{path}:{line_no}: {len(fields)} fields, expected {DESCRIPTOR_BYTES + 3}"
                    + (" (an empty line: DBoW2 would read it as a node)" if not fields else "")
                )
            p = int(fields[0])
            if not 0 <= p < line_no - 1:
                raise VocabularyFormatError(
                    f"{path}:{line_no}: parent {p} does not come before node {line_no - 1}"
                )
            parent.append(p)
            leaf.append(int(fields[1]) > 0)
            desc.append([int(v) for v in fields[2:-1]])
            weight.append(float(fields[-1]))
    vocab = Vocabulary(
        k=k,
        levels=levels,
        parent=np.array(parent, np.int64),
        descriptor=np.array(desc, np.uint8).reshape(-1, DESCRIPTOR_BYTES),
        is_leaf=np.array(leaf, bool),
        weight=np.array(weight, np.float64),
        scoring=scoring,
        weighting=weighting,
    )
    try:
        _children_table(vocab)
    except ValueError as err:
        raise VocabularyFormatError(f"{path}: {err}") from None
    return vocab


# --------------------------------------------------------------------------------------------------
# Command line: mounted as `jsve frontend vocabulary`


def image_files(inputs: Iterable[str | os.PathLike]) -> list[Path]:
    """Image files named on the command line: files as given, folders searched recursively (sorted)."""
    files: list[Path] = []
    for item in inputs:
        item = Path(item)
        if item.is_dir():
            files.extend(sorted(p for p in item.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES))
        elif item.is_file():
            files.append(item)
        else:
            raise FileNotFoundError(f"{item}: no such file or folder")
    return files


def add_vocabulary_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `jsve frontend vocabulary` (their one definition: jsve.cli.frontend mounts them as
    they are)."""
    parser.description = (
        "Train a DBoW2 text vocabulary (ORBvoc.txt format: TF-IDF weights, L1 scoring) for ORB-SLAM3 on ORB "
        "features of your images, extracted with ORB-SLAM3's settings; deterministic under --seed. Use it "
        "where ORB-SLAM3 asks for ORBvoc.txt (a real ORBvoc.txt works too)."
    )
    parser.add_argument(
        "images", nargs="+", metavar="IMAGES", help="image files or folders (searched recursively)"
    )
    # -o/--output, every jsve command's spelling of what it writes; the earlier --out still parses (a
    # unique prefix of --output).
    parser.add_argument(
        "-o", "--output", dest="output", required=True, metavar="VOC.txt", help="vocabulary file to write"
    )
    parser.add_argument(
        "--k", type=int, default=10, help="branching factor (default 10, as ORBvoc.txt; max 20)"
    )
    parser.add_argument(
        "--levels", type=int, default=6, help="tree depth L (default 6, as ORBvoc.txt; max 10)"
    )
    parser.add_argument(
        "--features", type=int, default=1000, help="ORB features per image (default 1000, ORB-SLAM3's EuRoC)"
    )
    parser.add_argument("--stride", type=int, default=1, help="use every N-th image (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the k-means++ draws (default 0)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_vocabulary(args: argparse.Namespace) -> int:
    """`jsve frontend vocabulary`: build and write; prints the size and the time. Returns the exit status."""
    import sys

    try:
        files = image_files(args.images)[:: max(1, args.stride)]
        if not files:
            raise FileNotFoundError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {' '.join(args.images)}")
        start = time.perf_counter()
        vocab = build_vocabulary(
            files, k=args.k, levels=args.levels, n_features=args.features, seed=args.seed,
            progress=not args.no_progress,
        )  # fmt: skip
        write_vocabulary(vocab, args.output)
    except (ValueError, FileNotFoundError) as err:
        print(f"jsve frontend vocabulary: {err}", file=sys.stderr)
        return 2
    seconds = time.perf_counter() - start
    depth = math.log(max(vocab.n_words, 1), max(vocab.k, 2))
    print(
        f"{args.output}: {vocab.n_words} words, {vocab.n_nodes} nodes (k={vocab.k}, L={vocab.levels}, "
        f"~k^{depth:.1f} words) from {vocab.n_descriptors} descriptors of {vocab.n_images} images "
        f"in {seconds:.1f} s"
    )
    return 0
