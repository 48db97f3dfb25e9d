"""jsve.io._groundtruth: ground truth from EuRoC / TUM / KITTI files, associated with the frames of a run."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest
from logfactory import make_run, same_bits
from scipy.spatial.transform import Rotation, Slerp

from jsve.cli import main as jsve_main
from jsve.io import _groundtruth as groundtruth
from jsve.io import _ingest as ingest
from jsve.io import _logs as logs
from jsve.io import _parquet as parquet
from jsve.io import _schema as schema

# ---------------------------------------------------------------------------------------------------
# Ground truth


def euroc_gt(shared_data) -> tuple[Path, np.ndarray, np.ndarray]:
    """V101 left-camera ground truth: (path, int64 ns stamps, [n, 7] p xyz + q wxyz), parsed with numpy."""
    path = shared_data / "euroc" / "groundtruth_left_cam" / "V101_GT.txt"
    text = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    stamps = np.array([int(line.split(",")[0].split(".")[0]) for line in text], dtype=np.int64)
    values = np.array([[float(v) for v in line.split(",")[1:8]] for line in text])
    return path, stamps, values


def with_stamps(t_ns: np.ndarray, seed: int = 0, **meta) -> schema.RunLog:
    run = make_run(len(t_ns), seed, with_gt=False, **meta)
    return dataclasses.replace(run, frames=run.frames.assign(t_ns=np.asarray(t_ns, dtype=np.int64)))


def test_euroc_exact_stamps_take_the_file_values(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    run = with_stamps(stamps[100:400])
    out = groundtruth.associate_ground_truth(run, path, "euroc")
    gt = out.frames[list(schema.GT_COLUMNS)].to_numpy()
    # Positions are the file's doubles; quaternions are normalised (the file has ~10 digits).
    np.testing.assert_allclose(gt[:, :3], values[100:400, :3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(gt[:, 3:], values[100:400, 3:], rtol=0, atol=1e-9)
    assert out.meta["gt_missing_frames"] == 0 and out.meta["gt_source"] == str(path)
    assert same_bits(out.frames[list(schema.REQUIRED_COLUMNS)], run.frames)
    logs.validate_run(out)  # a valid v1 run, ready to write


def test_euroc_interpolation_midpoints(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    k = np.arange(200, 500)
    t = stamps[k] + (stamps[k + 1] - stamps[k]) // 2  # half a period later
    out = groundtruth.associate_ground_truth(with_stamps(t), path)
    gt = out.frames[list(schema.GT_COLUMNS)].to_numpy()
    alpha = (t - stamps[k]) / (stamps[k + 1] - stamps[k])
    assert np.allclose(alpha, 0.5, atol=1e-8)
    p = values[k, :3] + alpha[:, None] * (values[k + 1, :3] - values[k, :3])
    np.testing.assert_allclose(gt[:, :3], p, rtol=0, atol=1e-9)
    # Oracle: scipy's Slerp (xyzw), between the two neighbouring samples.
    for i in range(0, len(k), 37):
        key = Rotation.from_quat(values[[k[i], k[i] + 1]][:, [4, 5, 6, 3]])
        q = Slerp([0.0, 1.0], key)([alpha[i]]).as_quat()[0][[3, 0, 1, 2]]
        assert min(np.abs(gt[i, 3:] - q).max(), np.abs(gt[i, 3:] + q).max()) < 1e-9


def test_int64_stamps_resolve_nanoseconds(shared_data):
    # 100 ns after a sample: evo's float seconds (spacing ~240 ns at 1.4e9 s) cannot tell it apart.
    path, stamps, values = euroc_gt(shared_data)
    t = stamps[300:310] + 100
    gt = groundtruth.associate_ground_truth(with_stamps(t), path).frames[list(schema.GT_POSITION)].to_numpy()
    alpha = 100 / (stamps[301:311] - stamps[300:310])
    expected = values[300:310, :3] + alpha[:, None] * (values[301:311, :3] - values[300:310, :3])
    np.testing.assert_allclose(gt, expected, rtol=0, atol=1e-12)
    assert not np.allclose(gt, values[300:310, :3], rtol=0, atol=1e-12)


def test_frames_outside_the_span_are_counted_and_warned(shared_data, caplog):
    path, stamps, values = euroc_gt(shared_data)
    t = np.concatenate([stamps[0] - np.array([3, 2, 1]) * 50_000_000, stamps[:50], stamps[-1] + [1, 2]])
    with caplog.at_level(logging.WARNING, logger="jsve.io._logs"):
        out = groundtruth.associate_ground_truth(with_stamps(t), path)
    missing = out.frames["gt_px"].isna().to_numpy()
    assert missing.tolist() == [True] * 3 + [False] * 50 + [True] * 2
    assert out.frames.loc[missing, list(schema.GT_COLUMNS)].isna().all(axis=None)
    assert out.meta["gt_missing_frames"] == 5
    assert any("5 of 55 frames have no ground truth" in r.getMessage() for r in caplog.records)


def test_gaps_wider_than_max_gap_are_not_interpolated(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    t = np.sort(np.concatenate([stamps[10:20], stamps[10:19] + 25_000_000]))
    out = groundtruth.associate_ground_truth(
        with_stamps(t), path, max_gap_ns=40_000_000
    )  # samples are 50 ms apart
    missing = out.frames["gt_px"].isna().to_numpy()
    assert np.array_equal(missing, ~np.isin(t, stamps))
    assert out.meta["gt_missing_frames"] == 9


def test_nearest_sample_without_interpolation(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    t = np.concatenate([stamps[40:45] + 10_000_000, stamps[45:50] + 40_000_000])
    out = groundtruth.associate_ground_truth(with_stamps(t), path, interpolate=False)
    np.testing.assert_array_equal(
        out.frames[list(schema.GT_POSITION)].to_numpy(),
        np.concatenate([values[40:45, :3], values[46:51, :3]]),
    )


def test_tum_equals_euroc(shared_data, tmp_path):
    path, stamps, values = euroc_gt(shared_data)
    tum = tmp_path / "gt.tum"
    lines = [
        f"{t // 10**9}.{t % 10**9:09d} " + " ".join(repr(float(v)) for v in (*row[:3], *row[4:], row[3]))
        for t, row in zip(stamps[:300], values[:300], strict=True)
    ]
    tum.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    run = with_stamps(np.concatenate([stamps[5:100], stamps[100:200] + 12_345_678]))
    a = groundtruth.associate_ground_truth(run, path, "euroc")
    b = groundtruth.associate_ground_truth(run, tum, "tum")
    assert same_bits(a.frames, b.frames)


def test_kitti_by_frame_index(shared_data):
    path = shared_data / "kitti" / "odometry_poses" / "04.txt"
    poses = np.loadtxt(path).reshape(-1, 3, 4)
    n = len(poses) + 3
    out = groundtruth.associate_ground_truth(with_stamps(np.arange(n) * 100_000_000), path, "kitti")
    gt = out.frames[list(schema.GT_COLUMNS)].to_numpy()
    np.testing.assert_array_equal(gt[: len(poses), :3], poses[:, :, 3])
    rot = Rotation.from_quat(gt[: len(poses), [4, 5, 6, 3]]).as_matrix()
    # KITTI stores 7 significant digits, so its matrices are orthonormal to ~1e-6.
    np.testing.assert_allclose(rot, poses[:, :, :3], atol=5e-6)
    assert np.isnan(gt[len(poses) :]).all() and out.meta["gt_missing_frames"] == 3


def test_kitti_with_times_file(shared_data):
    path = shared_data / "kitti" / "odometry_poses" / "00.txt"
    times = shared_data / "kitti" / "times_00.txt"
    t_ns = np.array([round(float(s) * 1e9) for s in times.read_text().split()], dtype=np.int64)
    poses = np.loadtxt(path).reshape(-1, 3, 4)
    run = with_stamps(np.concatenate([t_ns[10:20], (t_ns[20:30] + t_ns[21:31]) // 2]))
    out = groundtruth.associate_ground_truth(run, path, "kitti", kitti_times=times)
    p = out.frames[list(schema.GT_POSITION)].to_numpy()
    np.testing.assert_array_equal(p[:10], poses[10:20, :, 3])
    np.testing.assert_allclose(p[10:], (poses[20:30, :, 3] + poses[21:31, :, 3]) / 2, atol=1e-6)


def test_ground_truth_when_reading(shared_data, tmp_path):
    path, stamps, _ = euroc_gt(shared_data)
    plain = logs.write_log(with_stamps(stamps[:40], 1, sequence="V101"), tmp_path / "a.csv")
    own = make_run(40, 2, sequence="V101")
    logs.write_log(own, tmp_path / "b.csv")
    spec = {"V101": groundtruth.GroundTruth(path, "euroc")}
    result = ingest.read_logs(tmp_path, ground_truth=spec, workers=1, progress=False)
    a, b = result.runs
    assert a.has_ground_truth and a.meta["gt_missing_frames"] == 0
    assert same_bits(b.frames, own.frames)  # a log's own ground truth is kept
    single = logs.read_log(plain, ground_truth=path)
    assert same_bits(single.frames, a.frames)


def test_ground_truth_arguments_are_checked(shared_data):
    with pytest.raises(ValueError, match="fmt"):
        groundtruth.GroundTruth("x.txt", "csv")
    with pytest.raises(ValueError, match="kitti_times"):
        groundtruth.GroundTruth("x.txt", "euroc", kitti_times="t.txt")
    with pytest.raises(FileNotFoundError):
        groundtruth.associate_ground_truth(make_run(5, 0), shared_data / "no-such-file.txt")


def test_cli_ingest_with_ground_truth(shared_data, tmp_path, capsys):
    path, stamps, _ = euroc_gt(shared_data)
    logs.write_log(with_stamps(stamps[:30], 1, sequence="V101"), tmp_path / "logs" / "a.csv")
    out = tmp_path / "s.parquet"
    argv = ["ingest", str(tmp_path / "logs"), "-o", str(out), "--gt", str(path), "--gt-format", "euroc"]
    assert jsve_main([*argv, "--no-progress"]) == 0
    (run,) = parquet.read_parquet(out)
    assert run.has_ground_truth and run.meta["gt_missing_frames"] == 0


def test_cli_ingest_with_one_ground_truth_per_sequence(tmp_path, capsys):
    # --gt SEQ=FILE per sequence: each log gets its own sequence's trajectory, a sequence without one is
    # left without ground truth, and a plain FILE beside SEQ=FILE is refused
    folder = tmp_path / "logs"
    t0 = 1_403_715_274_000_000_000
    logs.write_log(with_stamps(t0 + 50_000_000 * np.arange(6), 1, sequence="V101"), folder / "a.csv")
    logs.write_log(with_stamps(t0 + 50_000_000 * np.arange(6), 2, sequence="V201"), folder / "b.csv")
    logs.write_log(with_stamps(t0 + 50_000_000 * np.arange(6), 3, sequence="MH01"), folder / "c.csv")
    v101 = _euroc_file(tmp_path / "v101.csv")
    v201 = _euroc_file(tmp_path / "v201.csv")
    v201.write_text(v201.read_text().replace(",0,1,1,0,0,0", ",2,1,1,0,0,0"))  # y = 2 m, not 0
    out = tmp_path / "s.parquet"
    argv = ["ingest", str(folder), "-o", str(out), "--no-progress"]
    argv += ["--gt", f"V101={v101}", "--gt", f"V201={v201}"]
    assert jsve_main(argv) == 0
    runs = {r.meta["sequence"]: r for r in parquet.read_parquet(out)}
    assert runs["V101"].has_ground_truth and runs["V201"].has_ground_truth
    assert not runs["MH01"].has_ground_truth
    np.testing.assert_allclose(runs["V101"].frames["gt_py"].to_numpy(), 0.0)
    np.testing.assert_allclose(runs["V201"].frames["gt_py"].to_numpy(), 2.0)
    mixed = [*argv[:5], "--gt", str(v101), "--gt", f"V201={v201}"]
    assert jsve_main(mixed) == 2
    assert "not both" in capsys.readouterr().err
    assert jsve_main([*argv[:5], "--gt", f"V101={v101}", "--gt", f"V101={v201}"]) == 2
    assert "given twice" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------------
# Values evo reads without a word (issue 12)


def _euroc_file(path: Path, n: int = 8) -> Path:
    rows = ["#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z"]
    rows += [f"{1_403_715_274_000_000_000 + i * 50_000_000},{0.1 * i},0,1,1,0,0,0" for i in range(n)]
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize(
    "row, reason",
    [
        ("1403715274150000000,0.3,nan,1,1,0,0,0", "column 'p_y' = 'nan': NaN or inf is not allowed"),
        ("1403715274150000000,0.3,0,1e300,1,0,0,0", "column 'p_z' = '1e300': beyond float32's range"),
        ("1403715274150000000,0.3,0,1,0,0,0,0", "columns 'q_w..q_z' = '0 0 0 0': not a unit quaternion"),
        ("1403715274150000000,0.3,0,1,NaN,0,0,0", "column 'q_w' = 'NaN': NaN or inf is not allowed"),
    ],
)
def test_nan_and_degenerate_ground_truth_is_refused_with_line_and_column(tmp_path, row, reason):
    # A NaN quaternion passed the old norm check (NaN > 1e-3 is False) and NaN positions were never checked.
    path = _euroc_file(tmp_path / "gt.csv")
    lines = path.read_text().splitlines()
    lines[4] = row  # line 5: the fourth pose
    path.write_text("\n".join(lines) + "\n")
    run = with_stamps(1_403_715_274_000_000_000 + 50_000_000 * np.arange(8))
    with pytest.raises(ValueError) as info:
        groundtruth.associate_ground_truth(run, path, "euroc")
    assert str(info.value).startswith(f"{path}:5: {reason}"), str(info.value)


def test_clean_ground_truth_still_associates(tmp_path):
    path = _euroc_file(tmp_path / "gt.csv")
    run = groundtruth.associate_ground_truth(
        with_stamps(1_403_715_274_000_000_000 + 50_000_000 * np.arange(8)), path
    )
    assert run.meta["gt_missing_frames"] == 0
    np.testing.assert_array_equal(run.frames["gt_px"].to_numpy(), 0.1 * np.arange(8))
