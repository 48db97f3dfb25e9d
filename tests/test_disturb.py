"""jsve.image._disturb: each disturbance against its definition (the dataset writer: test_datasets.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jsve.image import _disturb as d

W, H = 752, 480


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """A deterministic textured 752 x 480 grey image (smoothed noise plus edges)."""
    rng = np.random.default_rng(7)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 2.0)
    image = (image - image.min()) / (image.max() - image.min()) * 200 + 20
    image[100:200, 300:420] += 30
    return np.clip(image, 0, 255).astype(np.uint8)


# ---- seed paper disturbances -----------------------------------------------------------------------


def test_blur_kernel_mapping():
    assert [d.blur_kernel_size(n) for n in d.DISTURBANCES["blur"].levels] == [
        0, 5, 11, 15, 21, 25, 31, 35, 41, 45, 51
    ]  # fmt: skip
    with pytest.raises(ValueError, match="blur level"):
        d.blur_kernel_size(2.5)
    with pytest.raises(ValueError, match="blur level"):
        d.blur_kernel_size(-5)


@pytest.mark.parametrize("n", [5, 10, 25, 50])
def test_blur_is_opencv_gaussian_with_default_sigma(texture, n):
    k = d.blur_kernel_size(n)
    kernel = cv2.getGaussianKernel(k, 0)  # OpenCV's default sigma (or its fixed table for k <= 7)
    expected = cv2.sepFilter2D(texture, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT_101)
    # Both round a float result to uint8: they may differ by one DN at .5 ties.
    assert np.abs(d.gaussian_blur(texture, n).astype(int) - expected).max() <= 1
    if k > 7:  # the documented sigma is the one OpenCV uses beyond its small fixed tables
        np.testing.assert_allclose(cv2.getGaussianKernel(k, d.blur_sigma(n)), kernel, rtol=1e-6)


def test_blur_zero_is_a_copy(texture):
    out = d.gaussian_blur(texture, 0)
    assert out is not texture and np.array_equal(out, texture)


@pytest.mark.parametrize("s", d.DISTURBANCES["downsample"].levels)
def test_downsample_sizes(texture, s):
    small = d.downsample(texture, s, mode="calibration")
    assert small.shape == (round(H * s), round(W * s))
    assert d.downsample(texture, s).shape == (H, W)


def test_downsample_tenth_is_75_by_48(texture):
    assert d.downsample(texture, 0.1, mode="calibration").shape == (48, 75)


def test_downsample_loses_detail_but_keeps_mean(texture):
    gradients = []
    for s in (1.0, 0.5, 0.2):
        out = d.downsample(texture, s).astype(float)
        assert abs(out.mean() - texture.mean()) < 1.0  # area averaging preserves brightness
        gradients.append(np.abs(np.diff(out, axis=1)).mean())
    assert gradients[0] > gradients[1] > gradients[2]


def test_scaled_intrinsics_follow_opencv_pixel_centres():
    # A bright 2 x 2 block at source pixels (2i..2i+1, 2j..2j+1) becomes pixel (i, j) at s = 0.5;
    # the ray through the block's centre under the old calibration must hit (i, j) under the new one.
    image = np.zeros((H, W), np.uint8)
    i, j = 101, 57
    image[2 * j : 2 * j + 2, 2 * i : 2 * i + 2] = 255
    small = d.downsample(image, 0.5, mode="calibration")
    assert np.unravel_index(np.argmax(small), small.shape) == (j, i)
    fu, fv, cu, cv = 458.654, 457.296, 367.215, 248.375
    nfu, nfv, ncu, ncv = d.scale_intrinsics((fu, fv, cu, cv), (W, H), small.shape[::-1])
    x, y = (2 * i + 0.5 - cu) / fu, (2 * j + 0.5 - cv) / fv
    np.testing.assert_allclose((nfu * x + ncu, nfv * y + ncv), (i, j), atol=1e-9)


@pytest.mark.parametrize("n", d.DISTURBANCES["occlusion"].levels)
def test_occlusion_square_exact_and_centred(n):
    image = np.full((H, W), 255, np.uint8)
    out = d.occlusion(image, n)
    rows, cols = np.nonzero(out == 0)
    assert len(rows) == n * n
    assert rows.max() - rows.min() + 1 == n and cols.max() - cols.min() + 1 == n
    assert rows.min() == H - 1 - rows.max()  # as many rows above as below
    assert cols.min() == W - 1 - cols.max()
    assert np.all(out[out != 0] == 255)


def test_occlusion_odd_remainder_and_oversize():
    out = d.occlusion(np.full((H, W), 9, np.uint8), 51)
    rows, cols = np.nonzero(out == 0)
    assert (rows.min(), H - 1 - rows.max()) == (214, 215)  # half a pixel up and left
    assert np.all(d.occlusion(np.full((10, 20), 9, np.uint8), 30) == 0)


# ---- further disturbances --------------------------------------------------------------------------


def test_sensor_noise_statistics():
    flat = np.full((H, W), 128, np.uint8)
    out = d.sensor_noise(flat, 10.0, frame_seed=(0, 0, 1)).astype(float)
    # 361k samples: standard error of the mean 0.017 DN, of the std 0.012 DN; rounding adds 1/12 DN^2.
    assert abs(out.mean() - 128) < 0.1
    assert abs(out.std() - np.sqrt(100 + 1 / 12)) < 0.1
    again = d.sensor_noise(flat, 10.0, frame_seed=(0, 0, 1))
    other = d.sensor_noise(flat, 10.0, frame_seed=(0, 0, 2))
    assert np.array_equal(out, again) and not np.array_equal(out, other)
    assert np.array_equal(d.sensor_noise(flat, 0, frame_seed=3), flat)


def test_low_light_mean_and_noise_model():
    level, k, c, r = 200.0, 0.25, d.ELECTRONS_PER_DN, d.READ_NOISE_ELECTRONS
    flat = np.full((H, W), int(level), np.uint8)
    out = d.low_light(flat, k, frame_seed=1).astype(float)
    expected_var = k * (1 - k) * level / c + (1 - k * k) * (r / c) ** 2 + 1 / 12  # + quantisation
    assert abs(out.mean() - k * level) < 0.05
    assert abs(out.var() / expected_var - 1) < 0.05  # 361k samples: 0.2 % standard error
    gained = d.low_light(flat, k, frame_seed=1, auto_gain=True).astype(float)
    assert abs(gained.mean() - level) < 0.5 and gained.var() > 10 * out.var()
    assert np.array_equal(d.low_light(flat, 1.0, frame_seed=1), flat)
    with pytest.raises(ValueError, match="low-light"):
        d.low_light(flat, 0.0)


def test_low_light_gamma_brightens_shadows():
    flat = np.full((8, 8), 100, np.uint8)
    assert d.low_light(flat, 0.5, gamma=0.5, read_noise_e=0.0).mean() > d.low_light(flat, 0.5).mean()


@pytest.mark.parametrize("length", [3, 5, 15, 31])
def test_motion_blur_horizontal_and_vertical_are_boxes(texture, length):
    kernel = d.motion_blur_kernel(length, 0.0)
    centre = kernel.shape[0] // 2
    assert kernel.sum() == pytest.approx(1.0)
    assert np.count_nonzero(kernel) == length and np.allclose(kernel[centre][kernel[centre] > 0], 1 / length)
    np.testing.assert_allclose(d.motion_blur_kernel(length, 90.0), kernel.T, atol=1e-7)
    box = cv2.blur(texture, (length, 1), borderType=cv2.BORDER_REFLECT_101)
    assert np.abs(d.motion_blur(texture, length).astype(int) - box).max() <= 1  # rounding only


def test_motion_blur_diagonal_kernel_is_a_symmetric_line():
    kernel = d.motion_blur_kernel(20, 45.0)
    assert kernel.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(kernel, kernel[::-1, ::-1], atol=1e-7)
    rows, cols = np.nonzero(kernel)
    assert np.all(np.abs(rows - cols) <= 1)  # on the main diagonal (y down, 45 degrees)


def test_motion_blur_smooths_along_its_direction_only(texture):
    out = d.motion_blur(texture, 21, angle=0.0).astype(float)
    along = np.abs(np.diff(out, axis=1)).mean() / np.abs(np.diff(texture.astype(float), axis=1)).mean()
    across = np.abs(np.diff(out, axis=0)).mean() / np.abs(np.diff(texture.astype(float), axis=0)).mean()
    assert along < 0.3 < across


def test_haze_uniform_is_the_scattering_model(texture):
    tau, airlight = 1.3, d.HAZE_AIRLIGHT
    t = np.exp(-tau)
    expected = texture * t + airlight * (1 - t)
    assert np.abs(d.haze(texture, tau).astype(float) - expected).max() <= 0.5 + 1e-9


def test_fog_monotone_in_level(texture):
    outs = [d.haze(texture, tau).astype(float) for tau in d.DISTURBANCES["haze"].levels]
    contrast = [o.std() for o in outs]
    distance_to_airlight = [abs(o.mean() - d.HAZE_AIRLIGHT) for o in outs]
    assert all(a > b for a, b in zip(contrast, contrast[1:], strict=False))
    assert all(a > b for a, b in zip(distance_to_airlight, distance_to_airlight[1:], strict=False))


def test_patchy_haze_is_fixed_by_seed(texture):
    a = d.haze(texture, 1.5, patchiness=0.8, seed=(3, 0))
    assert np.array_equal(a, d.haze(texture, 1.5, patchiness=0.8, seed=(3, 0)))
    assert not np.array_equal(a, d.haze(texture, 1.5, patchiness=0.8, seed=(4, 0)))
    assert not np.array_equal(a, d.haze(texture, 1.5))


def _dirt_alpha(out: np.ndarray, value: float) -> np.ndarray:
    """Opacity recovered from dirt over a flat frame: out = value (1 - alpha + alpha s)."""
    return (value - out.astype(float)) / (value * (1 - d.DIRT_SCATTER))


def test_lens_dirt_identical_across_frames_for_a_seed():
    # Two different (flat) frames: the recovered blotches agree to the quantisation step.
    alpha_a = _dirt_alpha(d.lens_dirt(np.full((H, W), 120, np.uint8), 0.3, seed=5), 120)
    alpha_b = _dirt_alpha(d.lens_dirt(np.full((H, W), 240, np.uint8), 0.3, seed=5), 240)
    assert np.abs(alpha_a - alpha_b).max() < 1.0 / (120 * (1 - d.DIRT_SCATTER)) + 1e-9
    np.testing.assert_allclose(
        alpha_b, d.dirt_mask((H, W), 0.3, (5,)), atol=0.5 / (240 * (1 - d.DIRT_SCATTER)) + 1e-6
    )
    assert not np.allclose(d.dirt_mask((H, W), 0.3, (5,)), d.dirt_mask((H, W), 0.3, (6,)))


def test_lens_dirt_coverage_nested_and_reached():
    masks = [d.dirt_mask((H, W), c, (1,)) for c in (0.05, 0.2, 0.4, 0.6)]
    for c, mask in zip((0.05, 0.2, 0.4, 0.6), masks, strict=True):
        assert c <= mask.mean() < c + 0.1  # the last blotch overshoots by at most one blotch's share
    for low, high in zip(masks, masks[1:], strict=False):
        assert np.all(high >= low)


@pytest.mark.parametrize("name", list(d.DISTURBANCES))
def test_registry_levels_run_and_first_level_is_identity_or_seed(texture, name):
    function, levels, unit, doc = d.DISTURBANCES[name]
    assert callable(function) and unit and doc and len(levels) >= 8
    for level in levels:
        out = d.disturb_image(texture, name, level, seed=(0, 0), frame_seed=(0, 0, 1))
        assert out.dtype == np.uint8 and out.shape == (H, W)
    if name != "occlusion":  # every grid but the seed's occlusion starts at "no disturbance"
        assert np.array_equal(d.disturb_image(texture, name, levels[0], frame_seed=1), texture)


def test_unknown_names_and_parameters_are_refused(texture):
    with pytest.raises(ValueError, match="unknown disturbance"):
        d.disturb_image(texture, "rain", 1)
    with pytest.raises(ValueError, match="angle"):
        d.disturb_image(texture, "blur", 5, {"angle": 3})
