"""Tests of jsve.masks._masks: Algorithm 1 and the grid binning against plain-Python loops, KITTI MOTS
decoding against pycocotools on real annotations, PNG masks, masked runs end to end, malformed MOTS lines."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from logfactory import make_run
from pycocotools import mask as mask_util

from jsve.cli import main as cli_main
from jsve.core._numerics import round_half_away
from jsve.io import LogFormatError
from jsve.io import _keypoints as kpio
from jsve.io import _logs as logs
from jsve.io import _schema as schema
from jsve.io._keypoints import KeypointLog
from jsve.masks import _masks as masks
from jsve.masks._masks import MotsMasks, PngMasks, dynamic_keypoints, frame_counts, sve_bin_index

MOTS_0000 = "kitti/mots_instances/0000.txt"

# pycocotools 2.0.x under numpy 2 warns on every decode; the warning is about its own internals.
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation doesn't accept a copy keyword")

# --------------------------------------------------------------------------------------------------
# Oracles: plain Python, one keypoint at a time


def removed_loop(mask: np.ndarray, xy: np.ndarray, valid: np.ndarray) -> list[bool]:
    """Algorithm 1 as written: the mask at (floor x, floor y) and its +1 neighbours; off-image is unset."""
    height, width = mask.shape
    out = []
    for (x, y), ok in zip(xy.tolist(), valid.tolist(), strict=True):
        fx, fy = math.floor(x), math.floor(y)
        hit = False
        for cx, cy in ((fx, fy), (fx + 1, fy), (fx, fy + 1), (fx + 1, fy + 1)):
            if 0 <= cx < width and 0 <= cy < height and mask[cy][cx]:
                hit = True
        out.append(bool(ok) and hit)
    return out


def c_round(v: float) -> float:
    """C's round() of a float32 value (exact in double: |v| + 0.5 needs no rounding)."""
    return math.copysign(math.floor(abs(v) + 0.5), v)


def bin_loop(ux: float, uy: float, bounds) -> int:
    """ORB-SLAM3 Frame::PosInGrid in float32 (numpy float32 scalars), then the 8 x 8 SVE bin; -1 outside."""
    f = np.float32
    min_x, max_x, min_y, max_y = (f(b) for b in bounds)
    col = c_round(float((f(ux) - min_x) * (f(64) / (max_x - min_x))))
    row = c_round(float((f(uy) - min_y) * (f(48) / (max_y - min_y))))
    if not (0 <= col < 64 and 0 <= row < 48):
        return -1
    return int(row // 6) * 8 + int(col // 8)


def counts_loop(keep, inlier, grid_xy, bounds):
    bins = [0] * 64
    n = n_inl = 0
    for k, i, (ux, uy) in zip(keep.tolist(), inlier.tolist(), grid_xy.tolist(), strict=True):
        if not k:
            continue
        n += 1
        n_inl += int(i)
        b = bin_loop(ux, uy, bounds)
        if b >= 0:
            bins[b] += 1
    return n, n_inl, bins


def random_keypoints(rng, n: int, width: int, height: int) -> np.ndarray:
    """float32 positions: inside, fractional, integral, on and beyond every border, and far away."""
    x = rng.uniform(-3, width + 3, n)
    y = rng.uniform(-3, height + 3, n)
    integral = rng.random(n) < 0.2
    x[integral], y[integral] = np.round(x[integral]), np.round(y[integral])
    edges_x = [
        -1e9,
        -2.0,
        -1.5,
        -1.0,
        -0.5,
        -1e-3,
        0.0,
        0.5,
        width - 1.5,
        width - 1.0,
        width - 0.5,
        width,
        width + 0.5,
        1e9,
    ]
    edges_y = [
        -1e9,
        -2.0,
        -1.5,
        -1.0,
        -0.5,
        -1e-3,
        0.0,
        0.5,
        height - 1.5,
        height - 1.0,
        height - 0.5,
        height,
        height + 0.5,
        1e9,
    ]
    k = len(edges_x)
    x[:k], y[:k] = edges_x, rng.uniform(0, height, k)
    x[k : 2 * k], y[k : 2 * k] = rng.uniform(0, width, k), edges_y
    corners = np.array(np.meshgrid(edges_x, edges_y)).reshape(2, -1).T
    m = min(len(corners), n - 2 * k)
    x[2 * k : 2 * k + m], y[2 * k : 2 * k + m] = corners[:m, 0], corners[:m, 1]
    return np.stack([x, y], axis=1).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# Algorithm 1


@pytest.fixture(scope="module")
def frames():
    """6 frames of 17 x 23 masks (about 30 % set, plus border rows and columns) and 400 keypoints each."""
    rng = np.random.default_rng(11)
    height, width, n_frames, n = 17, 23, 6, 400
    m = rng.random((n_frames, height, width)) < 0.3
    m[0, 0, :] = m[1, -1, :] = m[2, :, 0] = m[3, :, -1] = True  # every border set somewhere
    m[5] = False
    xy = np.stack([random_keypoints(rng, n, width, height) for _ in range(n_frames)])
    valid = rng.random((n_frames, n)) < 0.85
    return m, xy, valid


def test_algorithm1_equals_loop_eagerly_and_under_jit(frames):
    m, xy, valid = frames
    kernel = jax.jit(dynamic_keypoints)
    for f in range(len(m)):
        expected = removed_loop(m[f], xy[f], valid[f])
        eager = dynamic_keypoints(jnp.asarray(m[f]), jnp.asarray(xy[f]), jnp.asarray(valid[f]))
        jitted = kernel(jnp.asarray(m[f]), jnp.asarray(xy[f]), jnp.asarray(valid[f]))
        assert np.asarray(eager).tolist() == expected
        assert np.asarray(jitted).tolist() == expected
    # The data exercise both outcomes on and off the borders (else the test could not fail).
    everything = [removed_loop(m[f], xy[f], valid[f]) for f in range(len(m))]
    assert 0.1 < np.mean(everything) < 0.9


def test_algorithm1_under_vmap_equals_stacked_loop(frames):
    m, xy, valid = frames
    batched = jax.jit(jax.vmap(dynamic_keypoints))(jnp.asarray(m), jnp.asarray(xy), jnp.asarray(valid))
    expected = [removed_loop(m[f], xy[f], valid[f]) for f in range(len(m))]
    assert np.asarray(batched).tolist() == expected


def test_algorithm1_border_cases():
    mask = np.zeros((4, 5), bool)
    mask[0, 0] = True  # top-left pixel
    mask[3, 4] = True  # bottom-right pixel
    xy = np.array(
        [
            [-0.5, -0.5],  # neighbours (-1,-1),(0,-1),(-1,0),(0,0): sees (0, 0)
            [-1.0, 0.0],  # (-1,0),(0,0): sees it
            [-1.01, 0.0],  # floor -2: (-2,0),(-1,0) only, never wraps to the last column
            [3.5, 2.5],  # (3,2),(4,2),(3,3),(4,3): sees (4, 3)
            [4.0, 3.0],  # (4,3) itself
            [4.5, 3.999],  # floor (4, 3)
            [5.0, 3.0],  # (5,3) and (6,3): off the image; no clamping onto column 4
            [0.99, 0.99],  # (0,0)
            [1.0, 1.0],  # (1,1),(2,1),(1,2),(2,2): none set
            [4.0, -1.0],  # row -1 and 0 of columns 4, 5: nothing set
            [0.0, 0.0],  # (0, 0) but padded
        ],
        np.float32,
    )
    valid = np.ones(len(xy), bool)
    valid[-1] = False
    got = np.asarray(dynamic_keypoints(jnp.asarray(mask), jnp.asarray(xy), jnp.asarray(valid))).tolist()
    assert got == [True, True, False, True, True, True, False, True, False, False, False]
    assert got == removed_loop(mask, xy, valid)


def test_algorithm1_checks_shapes():
    with pytest.raises(ValueError, match="mask must have shape"):
        dynamic_keypoints(jnp.zeros((2, 3, 4), bool), jnp.zeros((5, 2)), jnp.ones(5, bool))
    with pytest.raises(ValueError, match=r"xy must have shape \(N, 2\)"):
        dynamic_keypoints(jnp.zeros((3, 4), bool), jnp.zeros((5, 3)), jnp.ones(5, bool))
    with pytest.raises(ValueError, match=r"valid must have shape \(5,\)"):
        dynamic_keypoints(jnp.zeros((3, 4), bool), jnp.zeros((5, 2)), jnp.ones(4, bool))
    with pytest.raises(ValueError, match=r"grid_xy must have shape \(..., 2\)"):
        sve_bin_index(jnp.zeros((5, 3)), jnp.zeros(4))
    with pytest.raises(ValueError, match="bounds must be"):
        sve_bin_index(jnp.zeros((5, 2)), jnp.zeros(3))
    with pytest.raises(ValueError, match=r"one shape \(N,\), got \(5,\), \(4,\)"):
        frame_counts(jnp.ones(5, bool), jnp.ones(4, bool), jnp.zeros(5, jnp.int32))


# --------------------------------------------------------------------------------------------------
# Grid binning and counts


@pytest.mark.parametrize("bounds", [(0.0, 752.0, 0.0, 480.0), (-7.25, 760.5, -3.75, 484.125)])
def test_sve_bin_index_equals_posingrid_loop(bounds):
    rng = np.random.default_rng(5)
    min_x, max_x, min_y, max_y = bounds
    ux = rng.uniform(min_x - 10, max_x + 10, 3000).astype(np.float32)
    uy = rng.uniform(min_y - 10, max_y + 10, 3000).astype(np.float32)
    # Values whose scaled position sits at (or one float32 step around) a half: C rounding decides.
    step_x, step_y = (max_x - min_x) / 64, (max_y - min_y) / 48
    halves = np.arange(-1, 66) + 0.5
    exact_x = (min_x + halves * step_x).astype(np.float32)
    ux[: len(halves) * 3] = np.concatenate(
        [exact_x, np.nextafter(exact_x, np.float32(-1e9)), np.nextafter(exact_x, np.float32(1e9))]
    )
    exact_y = (min_y + halves[:50] * step_y).astype(np.float32)
    uy[-len(exact_y) :] = exact_y
    grid = np.stack([ux, uy], axis=1)
    expected = [bin_loop(a, b, bounds) for a, b in grid.tolist()]
    got = np.asarray(jax.jit(sve_bin_index)(jnp.asarray(grid), jnp.asarray(bounds))).tolist()
    assert got == expected
    assert np.asarray(sve_bin_index(jnp.asarray(grid), jnp.asarray(bounds))).tolist() == expected
    assert -1 in expected and set(range(64)) <= set(expected)


def test_round_half_away_is_exact_in_float32():
    v = jnp.asarray(np.array([0.49999997, -0.49999997, 0.5, -0.5, 1.5, 2.5, -2.5, 63.5, -0.2], np.float32))
    assert np.asarray(round_half_away(v)).tolist() == [
        0.0,
        -0.0,
        1.0,
        -1.0,
        2.0,
        3.0,
        -3.0,
        64.0,
        -0.0,
    ]


def test_round_half_away_is_cs_round_in_numpy_float64_too():
    # the largest double below 0.5 rounds to 0 in C (floor(v + 0.5) would give 1); halves go outwards
    below = np.nextafter(0.5, 0.0)
    v = np.array([below, -below, 0.5, -0.5, 1.5, 2.5, -2.5, 63.5, -0.2, 7.0])
    expected = [0.0, -0.0, 1.0, -1.0, 2.0, 3.0, -3.0, 64.0, -0.0, 7.0]
    assert round_half_away(v, xp=np).tolist() == expected
    assert np.signbit(round_half_away(v, xp=np)).tolist() == np.signbit(expected).tolist()


def test_frame_counts_equal_loop_under_jit_and_vmap():
    rng = np.random.default_rng(2)
    bounds = (0.0, 1241.0, 0.0, 376.0)
    n_frames, n = 5, 300
    grid = np.stack(
        [rng.uniform(-20, 1261, (n_frames, n)), rng.uniform(-20, 396, (n_frames, n))], axis=-1
    ).astype(np.float32)
    keep = rng.random((n_frames, n)) < 0.7
    inlier = rng.random((n_frames, n)) < 0.4
    expected = [counts_loop(keep[f], inlier[f], grid[f], bounds) for f in range(n_frames)]

    def kernel(k, i, g):
        return frame_counts(k, i, sve_bin_index(g, jnp.asarray(bounds)))

    batched = jax.jit(jax.vmap(kernel))(jnp.asarray(keep), jnp.asarray(inlier), jnp.asarray(grid))
    for f in range(n_frames):
        for result in (kernel(keep[f], inlier[f], grid[f]), [leaf[f] for leaf in batched]):
            n_ext, n_inl, bins = (np.asarray(r).tolist() for r in result)
            assert (n_ext, n_inl, bins) == expected[f]


# --------------------------------------------------------------------------------------------------
# KITTI MOTS on real annotations


def read_mots_plainly(path: Path) -> list[tuple[int, int, int, int, int, bytes]]:
    out = []
    for line in path.read_text().splitlines():
        frame, obj_id, class_id, height, width, rle = line.split(" ")
        out.append((int(frame), int(obj_id), int(class_id), int(height), int(width), rle.encode()))
    return out


def test_mots_decoding_equals_pycocotools_on_every_instance(shared_data):
    path = shared_data / MOTS_0000
    lines = read_mots_plainly(path)
    mots = MotsMasks(path)
    assert mots.shape == (lines[0][3], lines[0][4]) == (375, 1242)
    assert mots.frames == sorted({line[0] for line in lines})
    by_frame: dict[int, list] = {}
    for frame, obj_id, class_id, height, width, rle in lines:
        by_frame.setdefault(frame, []).append(
            (obj_id, class_id, mask_util.decode({"size": [height, width], "counts": rle}))
        )
    n_instances = 0
    for frame, expected in by_frame.items():
        instances = mots.instances(frame)
        assert [(i.obj_id, i.class_id) for i in instances] == [(o, c) for o, c, _ in expected]
        for instance, (_, _, reference) in zip(instances, expected, strict=True):
            mine = mots.instance_mask(instance)
            assert mine.shape == (375, 1242) and mine.dtype == bool
            assert np.array_equal(mine, reference.astype(bool))
            # The RLE validator decodes the same runs (column-major, zeros first) as pycocotools.
            runs = masks.rle_counts(mots.rle(instance)["counts"])
            flat = np.repeat(np.arange(len(runs)) % 2 == 1, runs)
            assert np.array_equal(flat.reshape(1242, 375).T, reference.astype(bool))
            n_instances += 1
        cars_people = [m for _, c, m in expected if c in (1, 2)]
        ignore = [m for _, c, m in expected if c == 10]
        union = np.any(cars_people, axis=0) if cars_people else np.zeros((375, 1242), bool)
        assert np.array_equal(mots.mask(frame), union)
        assert np.array_equal(mots[frame], union)
        assert np.array_equal(
            mots.ignore_mask(frame), np.any(ignore, axis=0) if ignore else np.zeros((375, 1242), bool)
        )
    assert n_instances == len(lines) > 100
    assert any(c == 10 for _, _, c, *_ in lines) and any(c == 2 for _, _, c, *_ in lines)


def test_mots_class_selection_and_lazy_iteration(shared_data):
    path = shared_data / MOTS_0000
    cars = MotsMasks(path, classes=[masks.CAR])
    people = MotsMasks(path, classes=[masks.PEDESTRIAN])
    everything = MotsMasks(path, classes=[1, 2, 10])
    frame = next(f for f in cars.frames if any(i.class_id == 2 for i in cars.instances(f)))
    assert np.array_equal(
        everything.mask(frame), cars.mask(frame) | people.mask(frame) | cars.ignore_mask(frame)
    )
    assert people.mask(frame).any() and not np.array_equal(cars.mask(frame), people.mask(frame))
    walk = cars.iter_masks(n_frames=cars.n_frames + 3)
    assert iter(walk) is walk  # a generator: one frame decoded at a time
    seen = 0
    for k, (f, m) in enumerate(walk):
        assert f == k and m.shape == (375, 1242)
        if f >= cars.n_frames or f not in cars.frames:
            assert not m.any()  # frames without annotations have empty masks
        seen += 1
    assert seen == cars.n_frames + 3 and len(cars) == cars.n_frames


def test_mots_image_size_comes_from_each_file(shared_data):
    folder = shared_data / "kitti/mots_instances"
    for name in ("0014.txt", "0018.txt", "0020.txt"):
        first = (folder / name).read_text().split("\n", 1)[0].split(" ")
        mots = MotsMasks(folder / name)
        assert mots.shape == (int(first[3]), int(first[4]))
        frame = mots.frames[0]
        assert mots.mask(frame).shape == mots.shape


# --------------------------------------------------------------------------------------------------
# Malformed MOTS files: file, line and field


def rle_of(mask: np.ndarray) -> str:
    return mask_util.encode(np.asfortranarray(mask.astype(np.uint8)))["counts"].decode()


GOOD = np.zeros((6, 8), bool)
GOOD[1:4, 2:5] = True


def mots_file(tmp_path, bad_line: str) -> Path:
    """Two good lines, then the bad one on line 3, then a good one."""
    good = rle_of(GOOD)
    lines = [f"0 1001 1 6 8 {good}", f"0 2001 2 6 8 {good}", bad_line, f"1 1001 1 6 8 {good}"]
    path = tmp_path / "0042.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "bad_line, field, needle",
    [
        ("0 1002 1 6 8", None, "expected 6 space-separated fields"),
        ("", None, "(an empty line)"),
        ("x 1002 1 6 8 {rle}", "frame", "field 'frame' = 'x': not a non-negative integer"),
        ("0 1002 -1 6 8 {rle}", "class_id", "not a non-negative integer"),
        ("0 1002 2 6 8 {rle}", "class_id", "object 1002 belongs to class 1"),
        ("0 1002 1 0 8 {rle}", "img_height", "must be positive"),
        ("0 1002 1 7 8 {rle}", "img_height", "the image is 7 x 8 here but 6 x 8 on the first line"),
        ("0 1002 1 6 8 {rle}!", "rle", "character '!' at position"),
        ("0 1002 1 6 8 {rle}\u00e9", "rle", "byte 0xc3 at position 8 is not valid"),
        ("0 1002 1 6 8 {rle}o", "rle", "ends in the middle of a run length"),
        ("0 1002 1 6 8 {small}", "rle", "the runs cover 24 pixels but the image has 6 x 8 = 48"),
        ("0 1001 1 6 8 {rle}", "obj_id", "repeats line 1 in frame 0"),
    ],
)
def test_malformed_mots_line(tmp_path, bad_line, field, needle):
    text = bad_line.format(rle=rle_of(GOOD), small=rle_of(np.ones((4, 6), bool)))
    path = mots_file(tmp_path, text)
    with pytest.raises(LogFormatError) as info:
        MotsMasks(path)
    err = info.value
    assert str(err).startswith(f"{path}:3: "), str(err)
    assert err.line == 3 and err.column == field
    assert needle in str(err), str(err)


def test_negative_run_is_refused():
    # '@' is 16 + 48: no continuation (0x20), sign bit (0x10) set, so the third run is 16 - 32 = -16.
    with pytest.raises(ValueError, match=r"run length 2 is negative \(-16\)"):
        masks.rle_counts(b"00@")
    assert masks.rle_counts(rle_of(GOOD).encode()).sum() == GOOD.size


def test_empty_mots_file(tmp_path):
    path = tmp_path / "0001.txt"
    path.write_text("")
    with pytest.raises(LogFormatError, match="no annotation lines"):
        MotsMasks(path)


def test_crlf_lines_decode(tmp_path):
    path = tmp_path / "0003.txt"
    path.write_bytes(f"0 1001 1 6 8 {rle_of(GOOD)}\r\n2 2001 2 6 8 {rle_of(~GOOD)}\r\n".encode())
    mots = MotsMasks(path)
    assert np.array_equal(mots.mask(0), GOOD) and np.array_equal(mots.mask(2), ~GOOD)


# --------------------------------------------------------------------------------------------------
# PNG masks


def test_png_masks_binary_and_instance_maps(tmp_path):
    binary = tmp_path / "binary"
    binary.mkdir()
    rng = np.random.default_rng(4)
    drawn = {k: rng.random((6, 8)) < 0.4 for k in (0, 1, 3)}
    for k, m in drawn.items():
        cv2.imwrite(str(binary / f"{k:06d}.png"), (m * 255).astype(np.uint8))
    source = PngMasks(binary)
    assert source.shape == (6, 8) and source.keys == [0, 1, 3]
    for k, m in drawn.items():
        assert np.array_equal(source.mask(k), m)
    with pytest.raises(FileNotFoundError, match="no mask PNG for frame 2"):
        source.mask(2)
    assert not PngMasks(binary, missing="empty").mask(2).any()

    instances = tmp_path / "instances"
    instances.mkdir()
    ids = np.zeros((6, 8), np.uint16)
    ids[0, :3], ids[1, :3], ids[2, :3] = 1003, 2001, 10000
    cv2.imwrite(str(instances / "000007.png"), ids)
    np.testing.assert_array_equal(PngMasks(instances, classes=[1]).mask(7), ids // 1000 == 1)
    np.testing.assert_array_equal(PngMasks(instances, classes=[1, 2]).mask(7), np.isin(ids // 1000, [1, 2]))
    np.testing.assert_array_equal(PngMasks(instances, classes=[10]).mask(7), ids == 10000)


def test_png_masks_errors(tmp_path):
    cv2.imwrite(str(tmp_path / "000001.png"), np.zeros((6, 8), np.uint8))
    cv2.imwrite(str(tmp_path / "frame_2.png"), np.zeros((5, 8), np.uint8))
    with pytest.raises(LogFormatError, match=r"frame_2.png: is 5 x 8 px, the first mask 6 x 8"):
        PngMasks(tmp_path).mask(2)
    cv2.imwrite(str(tmp_path / "1.png"), np.zeros((6, 8), np.uint8))
    with pytest.raises(LogFormatError, match="same frame number 1"):
        PngMasks(tmp_path)
    with pytest.raises(FileNotFoundError):
        PngMasks(tmp_path / "nothing-here")


# --------------------------------------------------------------------------------------------------
# Masked runs end to end


class ArrayMasks:
    """An in-memory mask source: one mask per frame index."""

    def __init__(self, stack: np.ndarray):
        self.stack = stack
        self.shape = stack.shape[1:]

    def mask(self, key: int) -> np.ndarray:
        return self.stack[key]


def consistent_pair(n_frames: int, seed: int, width: int = 96, height: int = 64, bounds=None):
    """A run and a side file that agree: the log's counts and bins are those of its keypoints."""
    rng = np.random.default_rng(seed)
    run = make_run(n_frames, seed=seed, image_size=[width, height])
    t_ns = run.frames["t_ns"].to_numpy()
    per_frame = rng.integers(0, 90, n_frames)
    per_frame[1] = 0  # a frame without keypoints
    frame = np.repeat(np.arange(n_frames), per_frame)
    xy = random_keypoints(rng, len(frame), width, height).astype(np.float64)
    rng.shuffle(xy)
    grid = (xy + rng.normal(scale=2.0, size=xy.shape)).astype(np.float32).astype(np.float64)  # "undistorted"
    meta = {"sequence": run.meta["sequence"], "run": run.meta["run"], "image_size": [width, height]}
    if bounds is not None:
        meta["image_bounds"] = list(bounds)
    kp = KeypointLog(
        meta,
        pd.DataFrame(
            {
                "t_ns": t_ns[frame],
                "x": xy[:, 0],
                "y": xy[:, 1],
                "ux": grid[:, 0],
                "uy": grid[:, 1],
                "octave": rng.integers(0, 8, len(frame)),
                "inlier": (rng.random(len(frame)) < 0.5).astype(np.int64),
            }
        ),
    )
    kp = kpio.validate_keypoints(kp)
    frames = run.frames.copy()
    b = kp.image_bounds
    for f in range(n_frames):
        rows = frame == f
        n, n_inl, bins = counts_loop(
            np.ones(rows.sum(), bool), kp.keypoints["inlier"].to_numpy()[rows], grid[rows], b
        )
        frames.loc[f, "n_extracted"], frames.loc[f, "n_inliers"] = n, n_inl
        frames.loc[f, list(schema.BIN_COLUMNS)] = bins
    return logs.validate_run(schema.RunLog(run.meta, frames)), kp, frame


def masked_counts_loop(run, kp, frame, stack):
    """Expected masked counts: the loops above, keypoint by keypoint."""
    xy = kp.keypoints[["x", "y"]].to_numpy()
    grid = kp.keypoints[["ux", "uy"]].to_numpy()
    inlier = kp.keypoints["inlier"].to_numpy()
    removed = np.zeros(len(xy), bool)
    rows = []
    for f in range(len(run.frames)):
        sel = np.flatnonzero(frame == f)
        removed[sel] = removed_loop(stack[f], xy[sel], np.ones(len(sel), bool))
        rows.append(counts_loop(~removed[sel], inlier[sel], grid[sel], kp.image_bounds))
    return removed, rows


@pytest.mark.parametrize("chunk_frames", [3, 16])
def test_apply_masks_equals_loops(chunk_frames):
    run, kp, frame = consistent_pair(11, seed=8, bounds=(-4.5, 100.25, -3.0, 66.5))
    rng = np.random.default_rng(9)
    stack = rng.random((11, 64, 96)) < 0.25
    result = masks.apply_masks(run, kp, ArrayMasks(stack), chunk_frames=chunk_frames)
    removed, rows = masked_counts_loop(run, kp, frame, stack)
    assert result.removed.tolist() == removed.tolist()
    assert 0 < removed.mean() < 1
    np.testing.assert_array_equal(result.n_removed, np.bincount(frame[removed], minlength=11))
    out = result.log.frames
    for f, (n, n_inl, bins) in enumerate(rows):
        assert out["n_extracted"].iloc[f] == n and out["n_inliers"].iloc[f] == n_inl
        assert out[list(schema.BIN_COLUMNS)].iloc[f].tolist() == bins
    untouched = [c for c in run.frames.columns if c not in ("n_extracted", "n_inliers") + schema.BIN_COLUMNS]
    pd.testing.assert_frame_equal(out[untouched], run.frames[untouched])
    assert result.log.meta["masks"] == "ArrayMasks"
    logs.validate_run(result.log)  # still a valid v1 run
    # Masks that are empty everywhere give back the log's own counts.
    same = masks.masked_log(run, kp, ArrayMasks(np.zeros_like(stack)))
    pd.testing.assert_frame_equal(same.frames, run.frames)


def test_apply_masks_with_real_mots_masks_and_stamp_keys(shared_data, tmp_path):
    mots = MotsMasks(shared_data / MOTS_0000)
    height, width = mots.shape
    run, kp, frame = consistent_pair(8, seed=4, width=width, height=height)
    stack = np.stack([mots.mask(f) for f in range(8)])
    assert stack[:5].any(axis=(1, 2)).all() and not stack[5:].any()  # frames with and without objects
    by_frame = masks.apply_masks(run, kp, mots, chunk_frames=3)
    removed, rows = masked_counts_loop(run, kp, frame, stack)
    assert by_frame.removed.tolist() == removed.tolist() and removed.any()
    assert [tuple(r) for r in by_frame.log.frames[["n_extracted", "n_inliers"]].to_numpy().tolist()] == [
        (n, i) for n, i, _ in rows
    ]
    # The same masks named by image stamp, as EuRoC names its images.
    folder = tmp_path / "stamped"
    folder.mkdir()
    for f, t in enumerate(run.frames["t_ns"]):
        cv2.imwrite(str(folder / f"{t}.png"), stack[f].astype(np.uint8) * 255)
    by_stamp = masks.apply_masks(run, kp, PngMasks(folder), key="t_ns")
    assert by_stamp.removed.tolist() == removed.tolist()


def test_apply_masks_refuses_what_does_not_fit():
    run, kp, _ = consistent_pair(6, seed=3)
    good = ArrayMasks(np.zeros((6, 64, 96), bool))
    with pytest.raises(ValueError, match=r"masks are 64 x 95 px .* image_size \[96, 64\]"):
        masks.apply_masks(run, kp, ArrayMasks(np.zeros((6, 64, 95), bool)))
    with pytest.raises(ValueError, match="key must be"):
        masks.apply_masks(run, kp, good, key="index")

    # A log whose n_extracted disagrees with its keypoints on frame 4: the side file's line of that frame.
    frames = run.frames.copy()
    frames.loc[4, "n_extracted"] += 1
    first_line = int(np.argmax(kp.keypoints["t_ns"].to_numpy() == frames["t_ns"].iloc[4])) + 3
    with pytest.raises(LogFormatError) as info:
        masks.apply_masks(schema.RunLog(run.meta, frames, "logs/r3.csv"), kp, good)
    assert f":{first_line}: column 't_ns'" in str(info.value)
    assert "frame 4 of logs/r3.csv: its keypoints give n_extracted" in str(info.value)
    assert masks.apply_masks(schema.RunLog(run.meta, frames), kp, good, verify=False).log is not None

    # One keypoint moved to the next bin: the counts still agree, the bins do not.
    frames = run.frames.copy()
    k = int(np.argmax(frames.loc[2, list(schema.BIN_COLUMNS)].to_numpy() > 0))
    frames.loc[2, f"bin_{k}"] -= 1
    frames.loc[2, f"bin_{(k + 1) % 64}"] += 1
    tampered = schema.RunLog(run.meta, frames)
    with pytest.raises(LogFormatError, match=f"its keypoints give bin_{k} = "):
        masks.apply_masks(tampered, kp, good)
    masks.apply_masks(tampered, kp, good, verify_bins=False)

    other = KeypointLog({**kp.meta, "run": kp.meta["run"] + 1}, kp.keypoints)
    with pytest.raises(LogFormatError, match="does not match the log's run"):
        masks.apply_masks(run, other, good)


def test_cli_mask_logs(tmp_path):
    run, kp, frame = consistent_pair(7, seed=12)
    log_path = logs.write_log(run, tmp_path / "in" / "r12.csv")
    kpio.write_keypoints(kp, kpio.keypoints_path(log_path))
    stack = np.random.default_rng(1).random((7, 64, 96)) < 0.3
    folder = tmp_path / "png"
    folder.mkdir()
    for f in range(7):
        cv2.imwrite(str(folder / f"{f:06d}.png"), stack[f].astype(np.uint8))
    assert cli_main(["mask-logs", str(log_path), "--png", str(folder), "-o", str(tmp_path / "out")]) == 0
    written = logs.read_log(tmp_path / "out" / "r12.csv")
    expected = masks.masked_log(run, kp, ArrayMasks(stack))
    pd.testing.assert_frame_equal(written.frames, expected.frames)
    assert written.meta["masks"].startswith("png:")
    # A side file that does not describe the log: exit 2, nothing written.
    frames = run.frames.copy()
    frames.loc[0, "n_inliers"] = max(0, frames.loc[0, "n_inliers"] - 1) if frames.loc[0, "n_inliers"] else 1
    frames.loc[0, "n_extracted"] = max(frames.loc[0, "n_extracted"], frames.loc[0, "n_inliers"])
    logs.write_log(schema.RunLog(run.meta, frames), log_path)
    assert cli_main(["mask-logs", str(log_path), "--png", str(folder), "-o", str(tmp_path / "out2")]) == 2
    assert not (tmp_path / "out2" / "r12.csv").exists()


def test_cli_mask_logs_refuses_two_inputs_of_one_file_name(tmp_path, capsys):
    """Two logs named r.csv in different folders would both be written to OUT/r.csv (the second
    silently replacing the first): exit 2, one line naming both, nothing written."""
    folder = tmp_path / "png"
    folder.mkdir()
    paths = []
    for k, name in enumerate(("a", "b")):
        run, kp, _ = consistent_pair(3, seed=20 + k)
        path = logs.write_log(run, tmp_path / name / "r.csv")
        kpio.write_keypoints(kp, kpio.keypoints_path(path))
        paths.append(str(path))
    for f in range(3):
        cv2.imwrite(str(folder / f"{f:06d}.png"), np.zeros((64, 96), np.uint8))
    out = tmp_path / "out"
    assert cli_main(["mask-logs", *paths, "--png", str(folder), "-o", str(out)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"jsve mask-logs: {paths[0]} and {paths[1]} would both be written to {out / 'r.csv'}; "
        "mask logs of the same file name into different folders (one run each)"
    ]
    assert not out.exists()


def test_cli_mask_logs_writes_every_masked_log_or_none(tmp_path, capsys):
    """A bad second log stops mask-logs with one line and exit 2, and the first log's masked copy is
    not left behind (all or nothing: an error inside the batch must not commit what came before)."""
    folder = tmp_path / "png"
    folder.mkdir()
    for f in range(3):
        cv2.imwrite(str(folder / f"{f:06d}.png"), np.zeros((64, 96), np.uint8))
    paths = []
    for k in range(2):
        run, kp, _ = consistent_pair(3, seed=30 + k)
        path = logs.write_log(run, tmp_path / "in" / f"r{k}.csv")
        if k == 0:  # only the first log has its keypoint side file
            kpio.write_keypoints(kp, kpio.keypoints_path(path))
        paths.append(str(path))
    out = tmp_path / "out"
    assert cli_main(["mask-logs", *paths, "--png", str(folder), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jsve mask-logs: ") and "r1" in err[0], err
    assert not out.exists() or [p for p in out.rglob("*") if p.is_file()] == []
