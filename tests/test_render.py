"""jsve.render: rendered EuRoC sequences (`jsve render`).

Oracles: a plain-Python slab test of every box for every sampled pixel (the vectorised, window-culled cast
must agree); OpenCV's distortion model (the rays must round-trip through it); the EuRoC layout as
jsve.image reads it; ORB-SLAM3's EuRoC.yaml and the real V1_01 gyro and frames in ../shared/data (skipped
when absent).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from jsve.image import Camera
from jsve.io._resume import StaleOutputError
from jsve.render import EUROC_CAM0, CameraRays, RenderConfig, render_sequence
from jsve.render import _raster as raster
from jsve.render import _scene as scene_mod
from jsve.render import _sequence as seq


@pytest.fixture(scope="module")
def rays():
    return CameraRays.of(EUROC_CAM0)


def test_rays_are_the_distorted_pixels(rays):
    # Every pixel's ray, pushed back through OpenCV's radial-tangential model, lands on that pixel: the image
    # is rendered with the lens distortion ORB-SLAM3 undoes. 1e-3 px: the float32 rays.
    h, w = rays.xn.shape
    u, v = rays.distort(rays.xn.astype(np.float64), rays.yn.astype(np.float64))
    px, py = np.meshgrid(np.arange(w), np.arange(h))
    assert np.abs(u - px).max() < 1e-3 and np.abs(v - py).max() < 1e-3
    np.testing.assert_allclose(np.linalg.norm(rays.rays, axis=0), 1.0, atol=1e-6)
    # At the principal point a pixel spans 1 / f radians (1 %: the pixel is 0.2 px off the principal point).
    centre = int(round(EUROC_CAM0.cy)) * w + int(round(EUROC_CAM0.cx))
    assert rays.footprint[centre] == pytest.approx(1 / math.sqrt(EUROC_CAM0.fx * EUROC_CAM0.fy), rel=0.01)


def _toy_scene(rng: np.random.Generator) -> scene_mod.Scene:
    positions = rng.uniform(-0.5, 0.5, (50, 3)) + [0, 0, 1.2]
    config = scene_mod.SceneConfig(margin_m=1.5, n_furniture=10, clearance_m=0.4)
    return scene_mod.make_scene(positions, rng, None, config)


def _slab_oracle(scene: scene_mod.Scene, o: np.ndarray, d: np.ndarray) -> tuple[float, int]:
    """Nearest hit of one ray, box by box in plain Python: (t, 6 box + face)."""
    best_t, best = math.inf, -1
    for axis in range(3):  # the room, from inside
        wall = scene.hi[0][axis] if d[axis] > 0 else scene.lo[0][axis]
        if d[axis] != 0:
            t = (wall - o[axis]) / d[axis]
            if t < best_t:
                best_t, best = t, 2 * axis + int(d[axis] > 0)
    for b in range(1, scene.n_boxes):
        t_near, t_far, near_axis = -math.inf, math.inf, 0
        for axis in range(3):
            t1 = (scene.lo[b][axis] - o[axis]) / d[axis]
            t2 = (scene.hi[b][axis] - o[axis]) / d[axis]
            if min(t1, t2) > t_near:
                t_near, near_axis = min(t1, t2), axis
            t_far = min(t_far, max(t1, t2))
        if t_near <= t_far and 0 < t_near < best_t:
            best_t, best = t_near, 6 * b + 2 * near_axis + int(d[near_axis] < 0)
    return best_t, best


def test_cast_equals_a_plain_slab_test(rays):
    rng = np.random.default_rng(0)
    scene = _toy_scene(rng)
    h, w = rays.xn.shape
    occluded = 0
    for _ in range(4):
        r_wc = cv2.Rodrigues(rng.normal(0, 1.0, 3))[0]
        p_wc = rng.uniform(-0.5, 0.5, 3) + [0, 0, 1.2]
        t, surface, d = raster.cast(scene, rays, r_wc, p_wc)
        pixels = rng.choice(h * w, 400, replace=False)
        for n in pixels:
            ray = (r_wc @ rays.rays[:, n].astype(np.float64)).astype(np.float32)
            t_ref, s_ref = _slab_oracle(scene, p_wc.astype(np.float32), ray)
            # float32 throughout; 1e-4 relative: rounding of the slab distances. A pixel exactly on an edge
            # may pick either face: compare the distance always, the surface where the faces are not tied.
            assert t[n] == pytest.approx(t_ref, rel=1e-4)
            if s_ref != surface[n]:
                assert abs(t[n] - t_ref) < 1e-4 * t_ref
            occluded += s_ref >= 6
    assert occluded > 50  # the furniture was in view, so the window culling was exercised


def test_visible_surfaces_equal_the_full_cast(rays):
    # The coarse grid refined near projected box edges finds exactly the surfaces of the per-pixel cast,
    # thin furniture included; poses inside the furniture's reach, so silhouettes cross the image.
    rng = np.random.default_rng(5)
    scene = _toy_scene(rng)
    furniture = []
    for _ in range(6):
        r_wc = cv2.Rodrigues(rng.normal(0, 1.0, 3))[0]
        p_wc = rng.uniform(-0.5, 0.5, 3) + [0, 0, 1.2]
        t, surface, _ = raster.cast(scene, rays, r_wc, p_wc)
        fast = raster.visible_surfaces(scene, rays, r_wc, p_wc)
        differ = np.flatnonzero(fast != surface)
        if len(differ):  # only where two faces tie (a ray through an edge): the same distance on either
            d = r_wc @ rays.rays[:, differ].astype(np.float64)
            tables = raster._Surfaces.of(scene)
            axis = tables.normal_axis[fast[differ]]
            t_fast = (tables.plane[fast[differ]] - p_wc[axis]) / d[axis, np.arange(len(differ))]
            np.testing.assert_allclose(t_fast, t[differ], rtol=1e-4)
        assert len(differ) < 10
        furniture.append(np.mean(surface >= 6))
    assert sum(f > 0.01 for f in furniture) >= 3  # furniture in view: silhouettes for the refinement


def test_mip_levels_are_registered():
    # A linear ramp stays a ramp under cv2.pyrDown; sampled through _MipMaps at a level-0 texel coordinate,
    # every level of the side-by-side layout must give the ramp's value there (pyrDown keeps the even texels:
    # registering level l at texel centres instead would slip by 2^(l-1) - 1/2 level-0 texels).
    height, width = 128, 4096  # level 6 is 64 texels wide: the samples stay clear of its borders
    ramp = np.tile(np.arange(width, dtype=np.float64) * 0.04 + 40, (height, 1))
    origin = scene_mod.mip_layout(height, width)
    mip = np.zeros((height, width * 3 // 2), np.float32)
    level = ramp.astype(np.float32)
    for x, y in origin:
        mip[y : y + level.shape[0], x : x + level.shape[1]] = level
        level = cv2.pyrDown(level)
    scene = scene_mod.Scene(
        lo=np.zeros((1, 3)),
        hi=np.ones((1, 3)),
        face_origin=np.zeros((1, 6, 2), np.float32),
        shade=np.ones((1, 6), np.float32),
        texel_m=0.005,
        mip=mip,
        mip_origin=origin.astype(np.float32),
        atlas=(),
        texture_source="ramp",
    )
    x = np.linspace(1000.0, 3000.0, 50).astype(np.float32)
    y = np.full(50, 64.0, np.float32)
    for lod in range(scene_mod.MIP_LEVELS - 1):
        maps = raster._MipMaps.of(scene, np.full(50, float(lod), np.float32))
        mx = np.concatenate([x, x]) * maps.scale + maps.shift_x
        my = np.concatenate([y, y]) * maps.scale + maps.shift_y
        sampled = cv2.remap(mip, mx.reshape(2, -1), my.reshape(2, -1), cv2.INTER_LINEAR)
        # 0.05 grey levels: cv2.remap's 1/32 texel steps at level 6 (2 level-0 texels, 0.08 grey) halved.
        np.testing.assert_allclose(sampled, np.tile(x * 0.04 + 40, (2, 1)), atol=0.05)


def test_room_encloses_the_trajectory_and_furniture_keeps_clear():
    rng = np.random.default_rng(1)
    positions = np.cumsum(rng.normal(0, 0.05, (400, 3)), axis=0) + [0, 0, 1.5]
    config = scene_mod.SceneConfig()
    lo, hi = scene_mod.layout(positions, rng, config)
    assert (lo[0] < positions.min(0) - 1.0).all() and (hi[0] > positions.max(0) + 1.0).all()
    assert len(lo) > config.n_furniture // 2  # pieces of several boxes each, most of them placed
    for b in range(1, len(lo)):
        assert (lo[b] >= lo[0] - 1e-9).all() and (hi[b] <= hi[0] + 1e-9).all()
        gap = np.linalg.norm(np.maximum(np.maximum(lo[b] - positions, positions - hi[b]), 0), axis=1)
        assert gap.min() >= config.clearance_m


def test_textures_are_deterministic_and_corner_rich():
    a = scene_mod.procedural_texture((256, 512), np.random.default_rng(2))
    b = scene_mod.procedural_texture((256, 512), np.random.default_rng(2))
    np.testing.assert_array_equal(a, b)
    corners = cv2.FastFeatureDetector.create(20).detect(np.clip(a, 0, 255).astype(np.uint8))
    # FAST 20 (ORB-SLAM3's iniThFAST): over 250 in 128k texels is over 700 in a 752 x 480 view at a texel per
    # pixel, before the pyramid's coarser levels add theirs (ORB-SLAM3 asks for 1000 in all).
    assert len(corners) > 250
    images = [np.random.default_rng(3).uniform(0, 255, (120, 160)).astype(np.float32)]
    m = scene_mod.mosaic_texture(images, (300, 700), np.random.default_rng(4))
    assert m.shape == (300, 700) and np.isfinite(m).all()


# --------------------------------------------------------------------------------------------------
# Whole sequences on a short synthetic trajectory


def _write_inputs(folder: Path, seconds: float = 2.0) -> tuple[Path, Path]:
    """A slow arc in ORB-SLAM3's EuRoC_left_cam layout (conjugated quaternions) and its 20 Hz stamps."""
    folder.mkdir(parents=True, exist_ok=True)
    t_ns = 1_000_000_000_000 + np.arange(int(seconds * 20) + 1, dtype=np.int64) * 50_000_000
    s = (t_ns - t_ns[0]) / 1e9
    p = np.stack([0.6 * np.cos(0.4 * s), 0.6 * np.sin(0.4 * s), 1.2 + 0.05 * s], 1)
    yaw = 0.4 * s + np.pi / 2
    # camera z (optical axis) horizontal along the motion, camera y down: R_wc columns (x, y, z)
    r_wc = np.stack([np.stack([np.sin(yaw), -np.cos(yaw), 0 * yaw], 1),
                     np.tile([0.0, 0.0, -1.0], (len(s), 1)),
                     np.stack([np.cos(yaw), np.sin(yaw), 0 * yaw], 1)], axis=2)  # fmt: skip
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(r_wc).as_quat()
    q_stored = np.stack([xyzw[:, 3], -xyzw[:, 0], -xyzw[:, 1], -xyzw[:, 2]], 1)  # the files' conjugate
    gt = folder / "V101_GT.txt"
    rows = [
        f"{t}," + ",".join(f"{v:.10f}" for v in (*pp, *qq))
        for t, pp, qq in zip(t_ns, p, q_stored, strict=True)
    ]
    gt.write_text("#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z\n" + "\n".join(rows) + "\n")
    stamps = folder / "stamps.txt"
    stamps.write_text("\n".join(str(t) for t in t_ns) + "\n")
    return gt, stamps


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return _write_inputs(tmp_path_factory.mktemp("render_inputs"))


def test_sequence_layout_and_determinism(tmp_path, inputs):
    gt, stamps = inputs
    one = render_sequence(gt, stamps, tmp_path / "a", frames="0:6", workers=1, progress=False)
    two = render_sequence(gt, stamps, tmp_path / "b", frames="0:6", workers=2, progress=False)
    assert one.status == two.status == "written" and one.rendered == 6
    mav0 = one.out / "mav0"
    listed = [line.split(",") for line in (mav0 / "cam0/data.csv").read_text().splitlines()[1:]]
    assert len(listed) == 6 and all(name == f"{t}.png" for t, name in listed)
    for _, name in listed:
        image = cv2.imread(str(mav0 / "cam0/data" / name), cv2.IMREAD_UNCHANGED)
        assert image is not None and image.shape == (480, 752) and image.dtype == np.uint8
        assert 20 < image.mean() < 230 and image.std() > 15  # exposed and textured
        # Same bytes whichever process rendered the frame.
        assert (mav0 / "cam0/data" / name).read_bytes() == (two.out / "mav0/cam0/data" / name).read_bytes()
    assert Camera.from_sensor_yaml(mav0 / "cam0/sensor.yaml") == EUROC_CAM0
    imu = np.loadtxt(mav0 / "imu0/data.csv", delimiter=",", skiprows=1)
    frames_ns = np.array([int(t) for t, _ in listed])
    assert imu[0, 0] <= frames_ns[0] and imu[-1, 0] >= frames_ns[-1]
    assert np.median(np.diff(imu[:, 0])) == pytest.approx(5e6, rel=1e-3)  # 200 Hz
    gravity = np.linalg.norm(imu[:, 4:7], axis=1).mean()
    assert gravity == pytest.approx(9.81, abs=0.3)  # specific force of a slow flight, plus bias
    gt_rows = np.loadtxt(mav0 / "state_groundtruth_estimate0/data.csv", delimiter=",", skiprows=1)
    assert gt_rows.shape[1] == 17
    np.testing.assert_allclose(np.linalg.norm(gt_rows[:, 4:8], axis=1), 1.0, atol=1e-9)
    manifest = json.loads((one.out / seq.MANIFEST_NAME).read_text())
    assert manifest["frames"] == 6 and manifest["texture"].startswith("procedural")
    # `jsve render` prints this estimate before rendering: each part within a third of what was written
    # (the PNG size depends on the texture; an estimate to plan a disk, not a measurement).
    n_frames, images, side = seq.sequence_size(gt, stamps, "0:6")
    pngs = sum(f.stat().st_size for f in (mav0 / "cam0/data").iterdir())
    tables = sum(
        (mav0 / name / "data.csv").stat().st_size for name in ("imu0", "state_groundtruth_estimate0")
    )
    assert n_frames == 6
    assert abs(images / pngs - 1) < 1 / 3, (images, pngs)
    assert abs(side / tables - 1) < 1 / 3, (side, tables)


def test_seed_resume_and_stale_output(tmp_path, inputs, monkeypatch):
    gt, stamps = inputs
    out = tmp_path / "r"
    first = render_sequence(gt, stamps, out, frames="0:4", workers=1, progress=False)
    again = render_sequence(gt, stamps, out, frames="0:4", workers=1, progress=False)
    assert again.status == "complete" and again.rendered == 0
    with pytest.raises(StaleOutputError, match="config.seed"):
        render_sequence(gt, stamps, out, frames="0:4", config=RenderConfig(seed=1), workers=1, progress=False)
    other = render_sequence(gt, stamps, tmp_path / "s", frames="0:4", config=RenderConfig(seed=1), workers=1,
                            progress=False)  # fmt: skip
    name = sorted((first.out / "mav0/cam0/data").iterdir())[0].name
    assert (first.out / "mav0/cam0/data" / name).read_bytes() != (
        other.out / "mav0/cam0/data" / name
    ).read_bytes()

    # A run that dies after its frames leaves OUT.partial; the next one keeps those frames.
    def crash(*args, **kwargs):
        raise RuntimeError("killed")

    monkeypatch.setattr(seq, "_write_side_files", crash)
    with pytest.raises(RuntimeError):
        render_sequence(gt, stamps, tmp_path / "t", frames="0:4", workers=1, progress=False)
    assert not (tmp_path / "t").exists() and len(list((tmp_path / "t.partial/mav0/cam0/data").iterdir())) == 4
    monkeypatch.undo()
    resumed = render_sequence(gt, stamps, tmp_path / "t", frames="0:4", workers=1, progress=False)
    assert resumed.status == "resumed" and resumed.rendered == 0 and resumed.kept == 4
    assert (resumed.out / seq.MANIFEST_NAME).is_file() and not (tmp_path / "t.partial").exists()


def test_bad_inputs_are_named(tmp_path, inputs):
    gt, stamps = inputs
    wrong = tmp_path / "trajectory.txt"
    wrong.write_text(gt.read_text())
    with pytest.raises(ValueError, match="<SEQ>_GT.txt"):
        render_sequence(wrong, stamps, tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="--frames must be A:B"):
        render_sequence(gt, stamps, tmp_path / "x", frames="3-5", progress=False)
    early = tmp_path / "early.txt"
    early.write_text("5\n6\n")
    with pytest.raises(ValueError, match="no frame stamp inside"):
        render_sequence(gt, early, tmp_path / "x", progress=False)


def test_command_line(tmp_path, inputs):
    from jsve.cli import main

    gt, stamps = inputs
    args = [
        "render",
        "--trajectory",
        str(gt),
        "--timestamps",
        str(stamps),
        "--frames",
        "0:2",
        "--workers",
        "1",
    ]
    assert main([*args, "-o", str(tmp_path / "c"), "--no-progress"]) == 0
    assert len(list((tmp_path / "c/mav0/cam0/data").iterdir())) == 2
    assert main([*args, "-o", str(tmp_path / "c"), "--no-progress", "--seed", "2"]) == 2  # another config


def test_imu_noise_option_picks_the_synthesised_stream(tmp_path, inputs, capsys):
    # --imu-noise datasheet: the sensor at rest only, whose dead reckoning agrees with the images; the default
    # in-flight model adds the correlated errors of the flying MAV. Both against the ideal readings.
    from jsve.cli import main
    from jsve.render._sequence import load_trajectory
    from jsve.sim import synthesize_imu

    gt, stamps = inputs
    args = ["render", "--trajectory", str(gt), "--timestamps", str(stamps)]
    args += ["--frames", "0:1", "--workers", "1"]
    error = {}
    for noise in ("in-flight", "datasheet"):
        out = tmp_path / noise
        assert main([*args, "--imu-noise", noise, "-o", str(out), "--no-progress"]) == 0
        rows = np.loadtxt(out / "mav0/imu0/data.csv", delimiter=",", comments="#")
        ideal = synthesize_imu(load_trajectory(str(gt)), np.random.default_rng(0), None)
        assert np.array_equal(rows[:, 0].astype(np.int64) // 1000, ideal.t_ns // 1000)
        bias = np.loadtxt(out / "mav0/state_groundtruth_estimate0/data.csv", delimiter=",", comments="#")
        # remove the stream's own random-walk biases (the ground truth's bias columns): what is left is noise
        # and, in flight, the correlated errors
        n = len(bias)
        left = rows[:n, 4:7] - ideal.accel[:n] - bias[:, 14:17]
        error[noise] = float(np.sqrt(np.mean(left**2)))
        config = json.loads((out / "jsve_render.json").read_text())["key"]["config"]
        assert config["imu_noise"]["accel_gm"] == (0.0 if noise == "datasheet" else 0.07)
    assert error["datasheet"] < error["in-flight"]
    assert main([*args, "--imu-noise", "datasheet", "--imu", str(gt), "-o", str(tmp_path / "x")]) == 2
    assert "cannot go with --imu" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------------
# Against the real data


def test_camera_is_orbslam3s_euroc_calibration(shared_data):
    text = (shared_data / "euroc/orbslam3_config/Monocular-Inertial.yaml").read_text()
    values = {}
    for line in text.splitlines():
        if line.startswith("Camera1.") or line.startswith("Camera.width") or line.startswith("Camera.height"):
            key, value = line.split(":", 1)
            values[key.strip()] = float(value.split("#")[0])
    c = EUROC_CAM0
    assert (c.width, c.height) == (values["Camera.width"], values["Camera.height"])
    assert (c.fx, c.fy, c.cx, c.cy) == tuple(values[f"Camera1.{k}"] for k in ("fx", "fy", "cx", "cy"))
    assert c.distortion == tuple(values[f"Camera1.{k}"] for k in ("k1", "k2", "p1", "p2"))


def test_ground_truth_rotations_are_stored_conjugated(shared_data):
    # ORB-SLAM3's EuRoC_left_cam files: read literally, the body rates do not fit the real V1_01 gyro; with
    # the quaternions conjugated (as jsve.sim.load_euroc_trajectory reads them) they do. Correlation per axis
    # after a 0.1 s average, over the flight.
    from jsve.sim import load_euroc_trajectory, read_imu_stream
    from jsve.sim._trajectory import (
        EUROC_CAM0_T_BS,
        matrix_to_quat,
        quat_mul,
        read_stamped_rows,
        trajectory_from_poses,
    )

    gt_dir = shared_data / "euroc/groundtruth_left_cam"
    imu = read_imu_stream(shared_data / "euroc/imu/V101.txt")
    conjugated = load_euroc_trajectory("V101", gt_dir)
    t_ns, values = read_stamped_rows(gt_dir / "V101_GT.txt", 7)
    q_cb = matrix_to_quat(EUROC_CAM0_T_BS[:3, :3].T)
    q_literal = np.asarray(quat_mul(values[:, 3:7], np.broadcast_to(q_cb, (len(t_ns), 4))))
    literal = trajectory_from_poses("literal", t_ns, values[:, :3], q_literal)

    def fit(trajectory) -> float:
        inside = (imu.t_ns > trajectory.frame_ns[0] + 10**9) & (imu.t_ns < trajectory.frame_ns[-1] - 10**9)
        omega = trajectory.angular_velocity(trajectory.seconds(imu.t_ns[inside]))
        box = np.ones(20) / 20
        return min(np.corrcoef(np.convolve(imu.gyro[inside, j], box, "valid"),
                               np.convolve(omega[:, j], box, "valid"))[0, 1] for j in range(3))  # fmt: skip

    assert fit(conjugated) > 0.9
    assert fit(literal) < 0.5


@pytest.mark.slow
def test_rendered_frames_serve_orb_slam3(tmp_path, shared_data):
    """ORB with ORB-SLAM3's settings finds as many features on rendered frames as on real EuRoC frames, spread
    wider, and consecutive frames match well enough for monocular initialisation, consistently with the GT."""
    euroc = shared_data / "euroc"
    texture = euroc / "V1_01_first95/mav0/cam0/data"
    gt, stamps = euroc / "groundtruth_left_cam/V101_GT.txt", euroc / "timestamps/V101.txt"
    result = render_sequence(
        gt, stamps, tmp_path / "V1_01", texture=texture, frames="800:806", progress=False
    )
    orb = cv2.ORB.create(1000, 1.2, 8, 19, 0, 2, cv2.ORB_HARRIS_SCORE, 31, 20)

    def features(path):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert image is not None
        keypoints, descriptors = orb.detectAndCompute(np.asarray(image), np.empty(0, np.uint8))
        xy = np.array([k.pt for k in keypoints])
        bins = np.unique((xy[:, 0] * 8 // 752) * 8 + xy[:, 1] * 8 // 480).size
        return xy, descriptors, bins

    real = [features(p) for p in sorted(texture.iterdir())[:6]]
    rendered = [features(p) for p in sorted((result.out / "mav0/cam0/data").iterdir())]
    assert min(len(f[0]) for f in rendered) >= 0.9 * min(len(f[0]) for f in real)
    assert np.mean([f[2] for f in rendered]) >= np.mean([f[2] for f in real])
    traj = seq.load_trajectory(euroc / "groundtruth_left_cam/V101_GT.txt")
    stamps = [int(p.stem) for p in sorted((result.out / "mav0/cam0/data").iterdir())]
    k, dist = EUROC_CAM0.matrix, np.array(EUROC_CAM0.distortion)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    for i in range(len(rendered) - 1):
        a, b = rendered[i], rendered[i + 1]
        pairs = [m[0] for m in matcher.knnMatch(a[1], b[1], k=2)
                 if len(m) == 2 and m[0].distance < 50 and m[0].distance < 0.9 * m[1].distance]  # fmt: skip
        pa = cv2.undistortPoints(a[0][[m.queryIdx for m in pairs]].reshape(-1, 1, 2), k, dist)
        pb = cv2.undistortPoints(b[0][[m.trainIdx for m in pairs]].reshape(-1, 1, 2), k, dist)
        e, mask = cv2.findEssentialMat(pa, pb, np.eye(3), cv2.RANSAC, 0.999, 1.0 / EUROC_CAM0.fx)
        assert int(mask.sum()) > 100
        _, rotation, _, _ = cv2.recoverPose(e, pa, pb, np.eye(3), mask=mask.copy())
        r, _ = seq.camera_poses(traj, np.array(stamps[i : i + 2]), np.zeros(1))
        truth = r[1, 0].T @ r[0, 0]
        angle = math.degrees(math.acos(np.clip((np.trace(rotation.T @ truth) - 1) / 2, -1, 1)))
        assert angle < 1.0  # the frame-to-frame rotation a 50 ms baseline gives, within a degree
