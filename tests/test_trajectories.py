"""jsve.io._trajectories: trajectory files read with evo, estimates paired with their reference, padding."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import sync
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from evo.tools import file_interface
from scipy.spatial.transform import Rotation

from jsve.io import _groundtruth as groundtruth
from jsve.io import _trajectories as trajectories
from jsve.io._errors import TrajectoryFileError
from jsve.io._trajectories import PosePair


def poses(rng, n: int) -> np.ndarray:
    """[n, 4, 4] random-walk poses (metres)."""
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)).as_matrix()
    out[:, :3, 3] = np.cumsum(rng.normal(scale=0.5, size=(n, 3)), axis=0)
    return out


@pytest.fixture
def tum(tmp_path):
    """A 50-pose TUM reference and two estimates: one offset by 3 ms, one lacking poses 7, 30 and 31."""
    rng = np.random.default_rng(4)
    ref, est = poses(rng, 50), poses(rng, 50)
    stamps = 1000.0 + 0.1 * np.arange(50)
    keep = np.ones(50, bool)
    keep[[7, 30, 31]] = False
    paths = [tmp_path / name for name in ("ref.tum", "a.tum", "b.tum")]
    for path, p, t in (
        (paths[0], ref, stamps),
        (paths[1], est, stamps + 0.003),
        (paths[2], est[keep], stamps[keep]),
    ):
        file_interface.write_tum_trajectory_file(str(path), PoseTrajectory3D(poses_se3=list(p), timestamps=t))
    return [str(p) for p in paths]


def test_tum_pairs_are_evo_associations(tum):
    ref_path, *est_paths = tum
    pairs = trajectories.read_pose_pairs(ref_path, est_paths, "tum")
    ref = file_interface.read_tum_trajectory_file(ref_path)
    assert [p.name for p in pairs] == est_paths
    for pair, path in zip(pairs, est_paths, strict=True):
        ref_a, est_a = sync.associate_trajectories(
            ref, file_interface.read_tum_trajectory_file(path), max_diff=0.01
        )
        np.testing.assert_array_equal(pair.ref, np.stack(ref_a.poses_se3))
        np.testing.assert_array_equal(pair.est, np.stack(est_a.poses_se3))
        np.testing.assert_array_equal(pair.t, ref_a.timestamps - ref.timestamps[0])
    assert [len(p.est) for p in pairs] == [50, 47]


def test_stamps_further_apart_than_t_max_diff_do_not_pair(tum):
    ref_path, a, _ = tum
    with pytest.raises(TrajectoryFileError, match=rf"^cannot associate {a} with {ref_path}: "):
        trajectories.read_pose_pairs(ref_path, [a], "tum", t_max_diff=0.001)  # a is 3 ms off


def test_kitti_pairs_by_index_with_optional_times(tmp_path):
    rng = np.random.default_rng(8)
    ref, est = poses(rng, 30), poses(rng, 30)
    for name, p in (("ref.txt", ref), ("est.txt", est), ("short.txt", est[:29])):
        file_interface.write_kitti_poses_file(str(tmp_path / name), PosePath3D(poses_se3=list(p)))
    times = tmp_path / "times.txt"
    np.savetxt(times, 5.0 + 0.1 * np.arange(30))
    (pair,) = trajectories.read_pose_pairs(tmp_path / "ref.txt", [tmp_path / "est.txt"], "kitti")
    assert pair.t is None and pair.name == str(tmp_path / "est.txt")
    # evo writes KITTI files with full precision: the poses read back exactly.
    np.testing.assert_array_equal(pair.ref, ref)
    np.testing.assert_array_equal(pair.est, est)
    (timed,) = trajectories.read_pose_pairs(
        tmp_path / "ref.txt", [tmp_path / "est.txt"], "kitti", kitti_times=times
    )
    np.testing.assert_allclose(timed.t, 0.1 * np.arange(30), rtol=0, atol=1e-12)
    with pytest.raises(TrajectoryFileError, match="short.txt has 29 poses but .*ref.txt has 30"):
        trajectories.read_pose_pairs(tmp_path / "ref.txt", [tmp_path / "short.txt"], "kitti")
    np.savetxt(times, np.arange(29.0))
    with pytest.raises(TrajectoryFileError, match="has 29 times but the reference has 30 poses"):
        trajectories.read_pose_pairs(tmp_path / "ref.txt", [], "kitti", kitti_times=times)
    with pytest.raises(ValueError, match="kitti_times applies to fmt='kitti'"):
        trajectories.read_pose_pairs(tmp_path / "ref.txt", [], "tum", kitti_times=times)


def test_unreadable_and_empty_files_name_the_file(tmp_path):
    missing = str(tmp_path / "missing.txt")
    with pytest.raises(TrajectoryFileError, match=rf"^cannot read {missing} as kitti: "):
        trajectories.read_trajectory(missing, "kitti")
    empty = tmp_path / "empty.tum"
    empty.write_text("# timestamp x y z qx qy qz qw\n")
    with pytest.raises(TrajectoryFileError, match=rf"^cannot read {empty} as tum: "):
        trajectories.read_trajectory(empty, "tum")  # evo refuses a file without rows
    with pytest.raises(ValueError, match="fmt must be one of"):
        trajectories.read_trajectory(empty, "csv")


def test_ground_truth_reads_the_same_formats():
    assert groundtruth.GT_FORMATS == trajectories.TRAJECTORY_FORMATS


def test_stack_pads_with_invalid_identity_poses():
    rng = np.random.default_rng(1)
    a, b = poses(rng, 5), poses(rng, 3)
    est, ref, valid = trajectories.stack_pose_pairs([PosePair("a", a, a[::-1]), PosePair("b", b, b[::-1])])
    assert est.shape == ref.shape == (2, 5, 4, 4) and valid.tolist() == [[True] * 5, [True] * 3 + [False] * 2]
    np.testing.assert_array_equal(ref[1, :3], b)
    np.testing.assert_array_equal(est[1, :3], b[::-1])
    np.testing.assert_array_equal(est[1, 3:], np.broadcast_to(np.eye(4), (2, 4, 4)))
    with pytest.raises(ValueError, match="at least one pair"):
        trajectories.stack_pose_pairs([])


def test_pose_pair_checks_shapes():
    with pytest.raises(ValueError, match="x: ref and est must both have shape"):
        PosePair("x", np.zeros((3, 4, 4)), np.zeros((2, 4, 4)))
    with pytest.raises(ValueError, match="x: no poses"):
        PosePair("x", np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
    with pytest.raises(ValueError, match=r"x: t must have shape \(3,\)"):
        PosePair("x", np.zeros((3, 4, 4)), np.zeros((3, 4, 4)), t=np.zeros(2))


# ---------------------------------------------------------------------------------------------------
# Values evo reads without a word (issue 12)


def _edit(path, line: int, field: int, text: str, delimiter: str = " ") -> None:
    """Set field `field` (0-based) of line `line` (1-based) of a text file."""
    lines = open(path).read().split("\n")
    fields = lines[line - 1].split(delimiter)
    fields[field] = text
    lines[line - 1] = delimiter.join(fields)
    open(path, "w").write("\n".join(lines))


@pytest.mark.parametrize(
    "field, text, column, reason",
    [
        (2, "nan", "ty", "NaN or inf is not allowed"),
        (0, "inf", "timestamp", "NaN or inf is not allowed"),
        (3, "1e300", "tz", "beyond float32's range"),
    ],
)
def test_a_nan_or_huge_tum_value_is_refused_with_line_and_column(tum, field, text, column, reason):
    # evo reads these; jsve's APE scored a NaN estimate 0.000000 m.
    ref_path, a, _ = tum
    _edit(a, 13, field, text)
    with pytest.raises(TrajectoryFileError) as info:
        trajectories.read_pose_pairs(ref_path, [a], "tum")
    assert str(info.value).startswith(f"{a}:13: column '{column}' = '{text}': {reason}")


@pytest.mark.parametrize("q", [("0", "0", "0", "0"), ("0.5", "0", "0", "0.5")])
def test_a_zero_or_far_from_unit_tum_quaternion_is_refused(tum, q):
    # evo turns a zero quaternion into the identity (with --align origin: 5.58 m instead of 0.02 m).
    ref_path, a, _ = tum
    for k, text in enumerate(q):
        _edit(a, 1, 4 + k, text)
    with pytest.raises(TrajectoryFileError) as info:
        trajectories.read_trajectory(a, "tum")
    assert str(info.value).startswith(f"{a}:1: columns 'qx..qw' = '{' '.join(q)}': not a unit quaternion")


def test_a_bad_euroc_line_is_named_after_its_comments(tmp_path):
    path = tmp_path / "gt.csv"
    rows = ["#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z"] + [
        f"{1000 + i}000000,{i},0,0,1,0,0,0" for i in range(5)
    ]
    path.write_text("\n".join(rows) + "\n")
    assert trajectories.read_trajectory(path, "euroc").num_poses == 5
    _edit(path, 4, 5, "NaN", ",")
    with pytest.raises(TrajectoryFileError, match=rf"^{path}:4: column 'q_x' = 'NaN': NaN or inf"):
        trajectories.read_trajectory(path, "euroc")


def test_a_kitti_pose_that_is_not_a_rotation_is_refused(tmp_path):
    path = tmp_path / "est.txt"
    rng = np.random.default_rng(2)
    file_interface.write_kitti_poses_file(str(path), PosePath3D(poses_se3=list(poses(rng, 6))))
    trajectories.read_trajectory(path, "kitti")
    lines = path.read_text().splitlines()
    lines[2] = " ".join(["0"] * 3 + [lines[2].split()[3]] + ["0"] * 3 + ["1"] + ["0"] * 3 + ["2"])
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(
        TrajectoryFileError, match=rf"^{path}:3: columns 'r11..r33' = '0 0 0 0 0 0 0 0 0': not a"
    ):
        trajectories.read_trajectory(path, "kitti")


def test_a_nan_kitti_time_is_refused(tmp_path):
    ref = tmp_path / "ref.txt"
    file_interface.write_kitti_poses_file(
        str(ref), PosePath3D(poses_se3=list(poses(np.random.default_rng(1), 4)))
    )
    times = tmp_path / "times.txt"
    times.write_text("0.0\n0.1\n\nnan\n0.3\n")
    with pytest.raises(TrajectoryFileError, match=rf"^{times}:4: column 'time' = 'nan': NaN or inf"):
        trajectories.read_pose_pairs(ref, [ref], "kitti", kitti_times=times)
