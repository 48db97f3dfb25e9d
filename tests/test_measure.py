"""jsve.image._measure and jsve.image._orb: ORB-SLAM3-style extraction, SVE bins, and counts on real EuRoC frames."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pandas as pd
import pytest

from jsve.image import _datasets as datasets
from jsve.image import _disturb as d
from jsve.image import _measure as m
from jsve.image import _orb as orb
from jsve.io._schema import BIN_COLUMNS

SEQUENCE = "euroc/V1_01_first95"


@pytest.fixture(scope="module")
def first_frames(request) -> tuple[list[np.ndarray], m.Camera, np.ndarray]:
    shared = request.getfixturevalue("shared_data")
    sequence = m.read_sequence(shared / SEQUENCE)
    return [m.read_image(p) for p in sequence.paths[:6]], sequence.camera, sequence.t_ns[:6]


# ---- pure pieces -------------------------------------------------------------------------------------


def test_features_per_level_sum_to_n_features():
    counts = m.OrbSettings().features_per_level()
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
    angle = m.intensity_centroid_angles(np.ascontiguousarray(image), np.array([[32.0, 32.0]]), 15)
    assert angle[0] == pytest.approx(expected, abs=1e-6)


def test_sve_bins_follow_orbslam3_grid_rounding():
    bounds = (0.0, 640.0, 0.0, 480.0)  # grid cells of 10 x 10 px
    points = np.array(
        [
            [4.9, 0.0],  # col round(0.49) = 0 -> bin 0
            [5.0, 0.0],  # col round(0.5) = 1 (C rounds halves away from zero) -> bin 0
            [75.0, 0.0],  # col 8 -> bin x 1
            [0.0, 55.0],  # row round(5.5) = 6 -> bin y 1 -> bin 8
            [634.9, 474.9],  # col 63, row 47 -> bin 63
            [635.0, 0.0],  # col 64: outside the grid, in no bin
            [-5.1, 0.0],  # col -1: outside
            [-5.0, 0.0],  # col round(-0.5) = -1: outside
        ]
    )
    bins = m.sve_bins(points, bounds)
    assert bins.sum() == 5
    assert (bins[0], bins[1], bins[8], bins[63]) == (2, 1, 1, 1)


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
    kept = m.distribute_quadtree(xy, response, width, height, n_wanted)
    assert kept.tolist() == _quadtree_oracle(xy, response, width, height, n_wanted)
    assert len(kept) <= n_wanted + 3  # the last split may overshoot by three nodes, never more


# ---- real frames -------------------------------------------------------------------------------------


def test_camera_from_euroc_sensor_yaml(shared_data):
    camera = m.Camera.from_sensor_yaml(shared_data / SEQUENCE / "mav0" / "cam0" / "sensor.yaml")
    assert (camera.width, camera.height) == (752, 480) and camera.fx == pytest.approx(458.654)
    min_x, max_x, min_y, max_y = camera.bounds()
    # Barrel distortion: the undistorted corners lie outside the image (ORB-SLAM3's mnMinX < 0 etc.).
    assert min_x < 0 < 752 < max_x and min_y < 0 < 480 < max_y


DESIGN_BLUR_REFERENCE = {5: 1000, 15: 1000, 25: 379, 35: 33, 45: 3}
"""DESIGN section 7: plain cv2.ORB_create with ORB-SLAM3's settings on the first V1_01 frame."""


def test_plain_opencv_orb_reproduces_design_reference(first_frames):
    image = first_frames[0][0]
    plain = m.OrbSettings(extractor="opencv", fallback=False)
    counts = {n: len(m.extract_orb(d.gaussian_blur(image, n), plain).xy) for n in DESIGN_BLUR_REFERENCE}
    assert counts == DESIGN_BLUR_REFERENCE


def test_blur_response_monotone_on_first_frame(first_frames):
    image = first_frames[0][0]
    levels = d.DISTURBANCES["blur"].levels
    with_fallback = [
        len(m.extract_orb(d.gaussian_blur(image, n), m.OrbSettings(extractor="opencv")).xy) for n in levels
    ]
    assert with_fallback[1] == 1000  # blur 5
    assert all(a >= b for a, b in zip(with_fallback, with_fallback[1:], strict=False))
    assert with_fallback[-1] < 200
    orbslam3 = {n: len(m.extract_orb(d.gaussian_blur(image, n)).xy) for n in (5, 15, 25, 35, 45, 50)}
    # Saturated at nFeatures (the quadtree may overshoot by up to 3 per level) until blur 25 ...
    assert all(1000 <= orbslam3[n] <= 1024 for n in (5, 15))
    # ... then falling: per-cell FAST 7 keeps some keypoints where plain FAST 20 finds almost none.
    assert orbslam3[25] > orbslam3[35] > orbslam3[45] > orbslam3[50] > DESIGN_BLUR_REFERENCE[45]


def test_counts_on_real_frames_are_sane(first_frames):
    images, camera, t_ns = first_frames
    counts = m.measure_frames(images, camera)
    n, inliers, frustum, bins = counts.n_extracted, counts.n_inliers, counts.n_frustum, counts.bins
    assert np.all((n >= 1000) & (n <= 1024))
    assert inliers[0] == 0 and frustum[0] == 0  # no previous frame
    # Consecutive 20 Hz frames of a slow flight: most keypoints are re-found and verified.
    assert np.all(inliers[1:] > 0.4 * n[1:]) and np.all(inliers[1:] <= np.minimum(n[1:], n[:-1]))
    assert np.all(frustum[1:] <= n[:-1]) and np.all(frustum[1:] >= inliers[1:])
    assert np.all(bins.sum(axis=1) <= n) and np.all(bins.sum(axis=1) >= 0.9 * n)
    table = m.visibility_table(t_ns, counts)
    assert list(table.columns[:4]) == ["t_ns", "n_extracted", "n_inliers", "n_frustum"]
    assert list(table.columns[4:68]) == list(BIN_COLUMNS)
    assert table["t_ns"].dtype == np.int64 and table["t_ns"].tolist() == t_ns.tolist()
    np.testing.assert_allclose(table["s_c"][1:], np.clip(inliers[1:] / frustum[1:], 0, 1), rtol=1e-6)
    assert np.all((table["s_b"] > 0.5) & (table["s_b"] <= 1.0))  # spread over the image, not clumped
    assert np.all(table["sve_option2"][1:] > 0.5)


def test_occlusion_lowers_homogeneity_on_real_frames(first_frames):
    images, camera, _ = first_frames
    clear = m.measure_frames(images[:2], camera)
    covered = m.measure_frames([d.occlusion(i, 400) for i in images[:2]], camera)
    table = m.visibility_table([0, 1], clear)
    occluded = m.visibility_table([0, 1], covered)
    # The quadtree moves the budget to the visible border, so S_b drops but does not collapse.
    assert occluded["s_b"][1] < table["s_b"][1] - 0.05
    assert covered.bins[1].reshape(8, 8)[3:5, 3:5].sum() < 0.2 * clear.bins[1].reshape(8, 8)[3:5, 3:5].sum()


def test_wrong_image_size_is_refused(first_frames):
    images, camera, _ = first_frames
    with pytest.raises(ValueError, match="calibration is for 752 x 480"):
        m.measure_frames([d.downsample(images[0], 0.5, mode="calibration")], camera)


def test_batch_tables_written_resumed_and_calibration_mode(shared_data, tmp_path):
    # A 4-frame copy of the real sequence (in a temporary folder, never the repository).
    source = tmp_path / "V1_4"
    cam = source / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    shutil.copy(shared_data / SEQUENCE / "mav0" / "cam0" / "sensor.yaml", cam / "sensor.yaml")
    frames = datasets.read_frame_list(shared_data / SEQUENCE / "mav0" / "cam0")[:4]
    for _, name in frames:
        shutil.copy(shared_data / SEQUENCE / "mav0" / "cam0" / "data" / name, cam / "data" / name)
    (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{n}\n" for t, n in frames))
    datasets.disturb_datasets(
        [source], tmp_path / "dist", ["downsample"], {"downsample": [1.0, 0.5]},
        {"downsample": {"mode": "calibration"}}, progress=False,
    )  # fmt: skip
    tables = m.measure_datasets(
        [tmp_path / "dist"], tmp_path / "tables", table_format="parquet", progress=False
    )
    names = sorted(p.relative_to(tmp_path / "tables").as_posix() for p in tables)
    assert names == [
        "dist/V1_4/downsample-0.5_mode=calibration.parquet",
        "dist/V1_4/downsample-1_mode=calibration.parquet",
    ]
    full, half = (pd.read_parquet(tmp_path / "tables" / n) for n in names[::-1])
    assert full["t_ns"].tolist() == [t for t, _ in frames] and len(half) == 4
    assert half["n_extracted"].mean() < full["n_extracted"].mean()  # a 376 x 240 image holds fewer
    stamp = {p: p.stat().st_mtime_ns for p in tables}
    m.measure_datasets([tmp_path / "dist"], tmp_path / "tables", table_format="parquet", progress=False)
    assert {p: p.stat().st_mtime_ns for p in tables} == stamp  # finished tables are kept
