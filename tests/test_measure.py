"""jsve.image._measure: SVE bins, counts, tables and resumable batch tables on real EuRoC frames.

ORB extraction itself is tested in test_orb.py."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest

from jsve.image import _datasets as datasets
from jsve.image import _disturb as d
from jsve.image import _measure as m
from jsve.io._schema import BIN_COLUMNS

SEQUENCE = "euroc/V1_01_first95"


# ---- pure pieces -------------------------------------------------------------------------------------


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


# ---- real frames -------------------------------------------------------------------------------------


def test_camera_from_euroc_sensor_yaml(shared_data):
    camera = m.Camera.from_sensor_yaml(shared_data / SEQUENCE / "mav0" / "cam0" / "sensor.yaml")
    assert (camera.width, camera.height) == (752, 480) and camera.fx == pytest.approx(458.654)
    min_x, max_x, min_y, max_y = camera.bounds()
    # Barrel distortion: the undistorted corners lie outside the image (ORB-SLAM3's mnMinX < 0 etc.).
    assert min_x < 0 < 752 < max_x and min_y < 0 < 480 < max_y


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


def _copy_frames(shared_data, source, n: int) -> list[tuple[int, str]]:
    """An n-frame copy of the real sequence at `source` (a temporary folder, never the repository)."""
    cam = source / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    shutil.copy(shared_data / SEQUENCE / "mav0" / "cam0" / "sensor.yaml", cam / "sensor.yaml")
    frames = datasets.read_frame_list(shared_data / SEQUENCE / "mav0" / "cam0")[:n]
    for _, name in frames:
        shutil.copy(shared_data / SEQUENCE / "mav0" / "cam0" / "data" / name, cam / "data" / name)
    (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{n}\n" for t, n in frames))
    return frames


def test_batch_tables_written_resumed_and_calibration_mode(shared_data, tmp_path):
    source = tmp_path / "V1_4"
    frames = _copy_frames(shared_data, source, 4)
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
    assert all(m.key_path(p).is_file() for p in tables)


def test_a_table_of_another_key_stops_the_batch_and_force_measures_it_again(shared_data, tmp_path, capsys):
    """measure resumes only what it measured under the same key: another setting, stride or frame, or a
    table without its key file, stops it before anything is written (StaleOutputError naming the
    difference; jsve measure: one line naming --force, exit 2); force measures those tables again."""
    from jsve.cli import main
    from jsve.io._resume import StaleOutputError

    roots = [tmp_path / "A", tmp_path / "B"]
    for root in roots:
        _copy_frames(shared_data, root, 3)
    out = tmp_path / "tables"
    run = dict(progress=False, orb=m.OrbSettings(n_features=500))
    tables = m.measure_datasets(roots, out, **run)
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    first = pd.read_csv(tables[0])

    with pytest.raises(
        StaleOutputError, match=r"2 tables measured under another key, e.g. A.csv: orb.n_features 500 != 600"
    ):
        m.measure_datasets(roots, out, progress=False, orb=m.OrbSettings(n_features=600))
    with pytest.raises(StaleOutputError, match="A.csv: stride 1 != 2"):
        m.measure_datasets(roots, out, stride=2, **run)
    image = sorted((roots[1] / "mav0" / "cam0" / "data").iterdir())[1]
    edited = image.read_bytes()
    image.write_bytes(m.cv2.imencode(".png", 255 - m.read_image(image))[1].tobytes())  # another frame
    with pytest.raises(StaleOutputError, match=r"1 tables .* e.g. B.csv: camera_hash"):
        m.measure_datasets(roots, out, **run)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == stamps  # nothing was written

    argv = [
        "measure",
        *map(str, roots),
        "-o",
        str(out),
        "--n-features",
        "500",
        "--workers",
        "1",
        "--no-progress",
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"jsve measure: {out} holds outputs of another job (1 tables")
    assert err[0].endswith("--force discards them and recomputes")
    assert main([*argv, "--force"]) == 0
    assert tables[0].stat().st_mtime_ns == stamps[tables[0]]  # A's table had its key: kept
    assert tables[1].stat().st_mtime_ns != stamps[tables[1]]
    fresh = m.measure_datasets([roots[1]], tmp_path / "fresh", **run)[0]
    pd.testing.assert_frame_equal(pd.read_csv(tables[1]), pd.read_csv(fresh))
    assert not pd.read_csv(tables[1]).equals(first)  # B's frames are A's no more
    assert m.measure_datasets(roots, out, **run) == tables  # resumed: equal keys now

    image.write_bytes(edited)
    m.key_path(tables[0]).unlink()  # a table without its key is never taken as finished
    with pytest.raises(StaleOutputError, match="A.csv: A.csv.key.json is missing"):
        m.measure_datasets([roots[0]], out, **run)
