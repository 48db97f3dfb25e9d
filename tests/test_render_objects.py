"""Dynamic objects in rendered sequences: paths, occlusion, instance masks (PNG and KITTI MOTS).

Oracles: the plain per-pixel cast (cast, itself checked against a slab test in test_render.py) for the
instance map; pycocotools, through jsve.masks' readers (themselves checked against pycocotools and the
real KITTI MOTS files), for the written instances_txt; geometry for the paths.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from test_render import _write_inputs

from jsve.masks import MotsMasks, PngMasks
from jsve.render import (
    EUROC_CAM0,
    CameraRays,
    ObjectsConfig,
    RenderConfig,
    SceneConfig,
    SensorModel,
    make_scene,
    render_frame_and_instances,
    render_sequence,
)
from jsve.render import _raster as raster
from jsve.render import _sequence as seq
from jsve.render._objects import CAR, PEDESTRIAN, place_objects

ROOMY = SceneConfig(margin_m=6.0, n_furniture=6)
"""A room with space for objects around the tests' small arc of camera centres."""


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return _write_inputs(tmp_path_factory.mktemp("objects_inputs"))


def _arc(n: int = 200) -> np.ndarray:
    s = np.linspace(0, 2 * np.pi, n)
    return np.stack([0.6 * np.cos(s), 0.6 * np.sin(s), 1.2 + 0 * s], 1)


def test_paths_keep_clear_of_cameras_furniture_and_each_other():
    positions = _arc()
    config = ObjectsConfig(cars=2, pedestrians=4, parked=1)
    for seed in range(5):
        rng = np.random.default_rng(seed)
        from jsve.render._scene import layout

        lo, hi = layout(positions, rng, ROOMY)
        objects = place_objects(positions, lo[0], hi[0], (lo[1:], hi[1:]), rng, config)
        assert list(objects.class_id) == [CAR, CAR, PEDESTRIAN, PEDESTRIAN, PEDESTRIAN, PEDESTRIAN]
        assert list(objects.obj_id) == [1001, 1002, 2001, 2002, 2003, 2004]
        assert objects.speed[0] == 0 and (objects.speed[1:] > 0).all()  # one parked
        swept_lo = np.minimum(objects.start, objects.end)
        swept_hi = np.maximum(objects.start, objects.end) + objects.size
        for i in range(len(objects)):
            gap = np.linalg.norm(
                np.maximum(np.maximum(swept_lo[i] - positions, positions - swept_hi[i]), 0), axis=1
            )
            assert gap.min() >= config.clearance_m
            assert (swept_lo[i] >= lo[0]).all() and (swept_hi[i] <= hi[0]).all()  # inside the room
            assert swept_lo[i][2] == lo[0][2]  # on the floor
            others = [(lo[b], hi[b]) for b in range(1, len(lo))]
            others += [(swept_lo[j], swept_hi[j]) for j in range(len(objects)) if j != i]
            for b_lo, b_hi in others:
                assert not (np.all(swept_lo[i] < b_hi) and np.all(b_lo < swept_hi[i]))


def test_objects_go_back_and_forth_along_their_paths():
    positions = _arc()
    rng = np.random.default_rng(3)
    from jsve.render._scene import layout

    lo, hi = layout(positions, rng, ROOMY)
    objects = place_objects(
        positions, lo[0], hi[0], (lo[1:], hi[1:]), rng, ObjectsConfig(cars=1, pedestrians=2)
    )
    length = np.linalg.norm(objects.end - objects.start, axis=1)
    t = np.linspace(0, 60, 1201)
    track = np.stack([objects.lo_at(s) for s in t])  # [T, M, 3]
    direction = (objects.end - objects.start) / length[:, None]
    along = np.einsum("tmk,mk->tm", track - objects.start, direction)
    off_path = track - objects.start - along[..., None] * direction
    np.testing.assert_allclose(off_path, 0, atol=1e-9)
    assert (along >= -1e-9).all() and (along <= length + 1e-9).all()
    speed = np.linalg.norm(np.diff(track, axis=0), axis=2) / np.diff(t)[:, None]
    turning = np.abs(np.diff(np.sign(np.diff(along, axis=0)), axis=0)).sum(1) > 0
    steady = ~np.concatenate([turning, [False]]) & ~np.concatenate([[False], turning])
    np.testing.assert_allclose(speed[steady], np.broadcast_to(objects.speed, speed.shape)[steady], rtol=1e-6)
    period = 2 * length / objects.speed
    np.testing.assert_allclose(np.stack([objects.lo_at(p) for p in period])[np.arange(3), np.arange(3)],
                               objects.lo_at(0.0), atol=1e-9)  # fmt: skip


def test_parking_every_object_keeps_the_scene_and_stills_it():
    positions = _arc()
    from jsve.render._scene import layout

    def objects(parked):
        rng = np.random.default_rng(7)
        lo, hi = layout(positions, rng, ROOMY)
        config = ObjectsConfig(cars=2, pedestrians=3, parked=parked)
        return place_objects(positions, lo[0], hi[0], (lo[1:], hi[1:]), rng, config)

    moving, parked = objects(0), objects("all")
    np.testing.assert_array_equal(moving.start, parked.start)
    np.testing.assert_array_equal(moving.size, parked.size)
    assert (parked.speed == 0).all() and (moving.speed > 0).all()
    for t in (0.0, 3.0, 17.5):
        np.testing.assert_array_equal(parked.lo_at(t), moving.lo_at(0.0))


@pytest.fixture(scope="module")
def scene():
    objects = ObjectsConfig(cars=2, pedestrians=4)
    return make_scene(_arc(), np.random.default_rng([0, 0]), None, ROOMY, objects=objects,
                      objects_rng=np.random.default_rng([0, 4]))  # fmt: skip


def _looking_at(scene, t_s: float, k: int):
    """A camera pose on the arc turned towards object k at time t_s: (r_wc [1, 3, 3], p_wc [1, 3])."""
    lo = scene.objects.lo_at(t_s)[k]
    target = lo + scene.objects.size[k] / 2
    p = np.array([0.6, 0.0, 1.2])
    z = (target - p) / np.linalg.norm(target - p)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], 1)[None], p[None]


def test_instance_map_is_the_cast_at_every_pixel(scene):
    rays = CameraRays.of(EUROC_CAM0)
    quiet = SensorModel(read_noise=0, shot_noise=0)
    seen = set()
    for k in range(len(scene.objects)):
        for t in (0.0, 4.0):
            at = scene.at(t)
            r, p = _looking_at(scene, t, k)
            _, instances = render_frame_and_instances(at, rays, (r, p), 1.0, np.random.default_rng(0), quiet)
            _, surface, _ = raster.cast(at, rays, r[0], p[0])
            expected = at.instance_ids()[surface // 6].reshape(instances.shape)
            np.testing.assert_array_equal(instances, expected)
            seen.update(np.unique(instances).tolist())
    assert set(scene.objects.obj_id.tolist()) <= seen  # every object is in view somewhere


def test_an_objects_texture_moves_with_it_and_the_room_stays(scene):
    """A still camera sees the room unchanged between two times, and the object moved by d exactly as a
    camera moved by -d sees the object standing: its texture moves with it."""
    rays = CameraRays.of(EUROC_CAM0)
    quiet = SensorModel(read_noise=0, shot_noise=0, optics_sigma=0, vignetting=0)
    k = int(np.argmax(scene.objects.speed))
    obj = scene.objects.obj_id[k]
    r, p = _looking_at(scene, 1.0, k)

    def render(t, p_wc):
        return render_frame_and_instances(scene.at(t), rays, (r, p_wc), 1.0, np.random.default_rng(0), quiet)

    (a, ia), (b, ib) = render(1.0, p), render(1.2, p)
    room = (ia == 0) & (ib == 0)
    assert room.mean() > 0.3 and (ia == obj).sum() > 2000 and not np.array_equal(ia, ib)
    np.testing.assert_array_equal(a[room], b[room])
    d = scene.objects.lo_at(1.2)[k] - scene.objects.lo_at(1.0)[k]
    assert np.linalg.norm(d) > 0.1
    c, ic = render(1.0, p - d)  # the camera moved back instead
    on = (ib == obj) & (ic == obj)  # the furniture hides it differently from the moved camera
    assert on.sum() > 0.5 * (ib == obj).sum()
    diff = np.abs(b[on].astype(int) - c[on].astype(int))
    assert diff.max() <= 2 and diff.mean() < 0.05  # float32 rounding of the texture coordinates only


def test_sequence_writes_masks_as_png_and_kitti_mots(tmp_path, inputs):
    gt, stamps = inputs
    config = RenderConfig(scene=ROOMY, objects=ObjectsConfig(cars=1, pedestrians=3, parked=1))
    one = render_sequence(gt, stamps, tmp_path / "a", frames="0:8", config=config, workers=1, progress=False)
    two = render_sequence(gt, stamps, tmp_path / "b", frames="0:8", config=config, workers=2, progress=False)
    cam0 = one.out / "mav0" / "cam0"
    stamps_ns = [int(line.split(",")[0]) for line in (cam0 / "data.csv").read_text().splitlines()[1:]]
    masks = sorted((cam0 / "masks").iterdir())
    assert [int(m.stem) for m in masks] == stamps_ns
    for m in masks:  # deterministic whichever process rendered the frame
        assert m.read_bytes() == (two.out / "mav0/cam0/masks" / m.name).read_bytes()
    mots = MotsMasks(cam0 / "instances.txt", classes=(1, 2))
    png = PngMasks(cam0 / "masks", classes=(1, 2))  # keyed by the stamp in the file name
    covered = []
    for k, t in enumerate(stamps_ns):
        instances = cv2.imread(str(cam0 / "masks" / f"{t}.png"), cv2.IMREAD_UNCHANGED)
        assert instances.dtype == np.uint16 and instances.shape == (480, 752)
        assert set(np.unique(instances).tolist()) <= {0, 1001, 2001, 2002, 2003}
        np.testing.assert_array_equal(mots.mask(k), instances > 0)
        np.testing.assert_array_equal(png.mask(t), instances > 0)
        covered.append((instances > 0).mean())
    manifest = json.loads((one.out / seq.MANIFEST_NAME).read_text())
    assert [o["obj_id"] for o in manifest["objects"]] == [1001, 2001, 2002, 2003]
    assert manifest["objects"][0]["speed_mps"] == 0
    assert manifest["masks"]["mask_share_mean"] == pytest.approx(np.mean(covered), abs=1e-4)
    assert manifest["masks"]["mask_share_max"] == pytest.approx(np.max(covered), abs=1e-4)
    assert manifest["key"]["config"]["objects"]["cars"] == 1


def test_a_scene_without_objects_keeps_its_key(tmp_path, inputs):
    """Datasets rendered before objects existed stay complete: their key has no objects entry."""
    gt, stamps = inputs
    key = seq._key(str(gt), str(stamps), None, None, np.array([1, 2]), RenderConfig())
    assert "objects" not in key["config"]
    key = seq._key(
        str(gt), str(stamps), None, None, np.array([1, 2]), RenderConfig(objects=ObjectsConfig(cars=1))
    )
    assert key["config"]["objects"]["cars"] == 1


def test_command_line_objects(tmp_path, inputs, capsys):
    from jsve.cli import main

    gt, stamps = inputs
    base = ["render", "--trajectory", str(gt), "--timestamps", str(stamps), "--frames", "0:2",
            "--workers", "1", "--no-progress", "--yes"]  # fmt: skip
    assert main([*base, "--cars", "1", "--parked", "some", "-o", str(tmp_path / "x")]) == 2
    assert "--parked must be a count or 'all', got 'some'" in capsys.readouterr().err
    assert main([*base, "--cars", "40", "--room-margin", "3", "-o", str(tmp_path / "y")]) == 2
    assert "object 1 of 40 (car) found no path" in capsys.readouterr().err
    assert not (tmp_path / "y").exists() and not (tmp_path / "y.partial").exists()  # refused before any work
    assert (
        main([*base, "--cars", "1", "--pedestrians", "1", "--parked", "all", "-o", str(tmp_path / "z")]) == 0
    )
    assert "2 objects cover" in capsys.readouterr().out
    assert (tmp_path / "z/mav0/cam0/instances.txt").is_file()
