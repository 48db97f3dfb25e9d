"""jsve.image._orb: ORB extraction as ORB-SLAM3 does it, against ORB's definition, a node-by-node oracle
of ORBextractor::DistributeOctTree, and plain OpenCV on a real EuRoC frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jsve.image import _disturb as d
from jsve.image import _orb as orb

# ---- pure pieces -------------------------------------------------------------------------------------


def test_features_per_level_sum_to_n_features():
    counts = orb.OrbSettings().features_per_level()
    assert (
        sum(counts) == 1000
        and counts[0] == 217
        and all(a > b for a, b in zip(counts, counts[1:], strict=False))
    )


def test_ic_disc_is_orbs_symmetric_disc():
    # u_max of ORB's 31 x 31 patch (Rublee et al. 2011; the table every ORB implementation derives).
    assert orb._disc_half_widths(15).tolist() == [15, 15, 15, 15, 14, 14, 14, 13, 13, 12, 11, 10, 9, 8, 6, 3]


@pytest.mark.parametrize(("axis", "expected"), [(1, 0.0), (0, 90.0)])
def test_intensity_centroid_points_up_the_gradient(axis, expected):
    ramp = np.arange(64, dtype=np.float64)
    image = np.broadcast_to(ramp[None, :] if axis == 1 else ramp[:, None], (64, 64)).astype(np.uint8)
    angle = orb.intensity_centroid_angles(np.ascontiguousarray(image), np.array([[32.0, 32.0]]), 15)
    assert angle[0] == pytest.approx(expected, abs=1e-6)


def _quadtree_oracle(xy, response, width, height, n_wanted):
    """Plain-Python, node-by-node ORBextractor::DistributeOctTree (the shape of the C++ loop)."""
    xs, ys = xy[:, 0].tolist(), xy[:, 1].tolist()
    n_initial = max(1, int(math.floor(width / height + 0.5)))
    step = width / n_initial
    nodes, next_id = {}, 0
    for c in range(n_initial):
        members = [i for i in range(len(xs)) if min(int(xs[i] / step), n_initial - 1) == c]
        if members:
            nodes[next_id] = (int(step * c), 0, int(step * (c + 1)), int(height), members)
            next_id += 1

    def divide(node):
        x0, y0, x1, y1, members = node
        mx, my = x0 + math.ceil((x1 - x0) / 2), y0 + math.ceil((y1 - y0) / 2)
        boxes = [(x0, y0, mx, my), (mx, y0, x1, my), (x0, my, mx, y1), (mx, my, x1, y1)]
        quarters = [[], [], [], []]
        for i in members:
            quarters[(xs[i] >= mx) + 2 * (ys[i] >= my)].append(i)
        return [(*b, q) for b, q in zip(boxes, quarters, strict=True) if q]

    while True:
        before, expandable = len(nodes), []
        for key in list(nodes):
            if len(nodes[key][4]) > 1:
                for child in divide(nodes.pop(key)):
                    nodes[next_id] = child
                    if len(child[4]) > 1:
                        expandable.append(next_id)
                    next_id += 1
        if len(nodes) >= n_wanted or len(nodes) == before:
            break
        if len(nodes) + 3 * len(expandable) > n_wanted:
            while True:
                before = len(nodes)
                order = sorted(expandable, key=lambda k: (len(nodes[k][4]), nodes[k][0]))
                expandable = []
                for key in reversed(order):
                    for child in divide(nodes.pop(key)):
                        nodes[next_id] = child
                        if len(child[4]) > 1:
                            expandable.append(next_id)
                        next_id += 1
                    if len(nodes) >= n_wanted:
                        break
                if len(nodes) >= n_wanted or len(nodes) == before:
                    break
            break
    return sorted(max(node[4], key=lambda i: (response[i], -i)) for node in nodes.values())


@pytest.mark.parametrize("seed", range(6))
def test_quadtree_matches_node_by_node_oracle(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000))
    width, height = float(rng.integers(40, 760)), float(rng.integers(30, 500))
    clustered = rng.normal([width / 3, height / 2], [width / 10, height / 8], (n // 2, 2))
    xy = np.concatenate([rng.uniform(0, 1, (n - n // 2, 2)) * [width, height], clustered])
    xy = np.clip(np.round(xy, 1), 0, [width - 1, height - 1])  # rounding makes duplicates and ties
    response = rng.integers(0, 40, n).astype(np.float32)
    n_wanted = int(rng.integers(1, 400))
    kept = orb.distribute_quadtree(xy, response, width, height, n_wanted)
    assert kept.tolist() == _quadtree_oracle(xy, response, width, height, n_wanted)
    assert len(kept) <= n_wanted + 3  # the last split may overshoot by three nodes, never more


# ---- real frames -------------------------------------------------------------------------------------


DESIGN_BLUR_REFERENCE = {5: 1000, 15: 1000, 25: 379, 35: 33, 45: 3}
"""DESIGN section 7: plain cv2.ORB_create with ORB-SLAM3's settings on the first V1_01 frame."""


def test_plain_opencv_orb_reproduces_design_reference(first_frames):
    image = first_frames[0][0]
    plain = orb.OrbSettings(extractor="opencv", fallback=False)
    counts = {n: len(orb.extract_orb(d.gaussian_blur(image, n), plain).xy) for n in DESIGN_BLUR_REFERENCE}
    assert counts == DESIGN_BLUR_REFERENCE


def test_blur_response_monotone_on_first_frame(first_frames):
    image = first_frames[0][0]
    levels = d.DISTURBANCES["blur"].levels
    with_fallback = [
        len(orb.extract_orb(d.gaussian_blur(image, n), orb.OrbSettings(extractor="opencv")).xy)
        for n in levels
    ]
    assert with_fallback[1] == 1000  # blur 5
    assert all(a >= b for a, b in zip(with_fallback, with_fallback[1:], strict=False))
    assert with_fallback[-1] < 200
    orbslam3 = {n: len(orb.extract_orb(d.gaussian_blur(image, n)).xy) for n in (5, 15, 25, 35, 45, 50)}
    # Saturated at nFeatures (the quadtree may overshoot by up to 3 per level) until blur 25 ...
    assert all(1000 <= orbslam3[n] <= 1024 for n in (5, 15))
    # ... then falling: per-cell FAST 7 keeps some keypoints where plain FAST 20 finds almost none.
    assert orbslam3[25] > orbslam3[35] > orbslam3[45] > orbslam3[50] > DESIGN_BLUR_REFERENCE[45]
