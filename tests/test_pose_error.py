"""jsve.core._pose_error: APE and RPE of many padded pose pairs, equal to run_error of one-segment runs and
to evo (metrics.APE and metrics.RPE after PosePath3D.align / align_origin) for every pose relation, delta
and delta unit, on random trajectories and on the real KITTI 00 ORB-SLAM estimate; the single-run kernels
eager == jit == vmap (a stacked loop), their gradients against central differences.

Tolerances: rel 1e-9 against evo in float64 (measured: 5e-12 at worst, KITTI's angle RPE; evo sums,
projects rotations (an SVD) and multiplies 4x4 matrices in other orders). Values that are 0 in exact
arithmetic (KITTI's first poses coincide: the minimum angle APE) are rounding noise on both sides, of order
1e-15; they are compared to an absolute 1e-12 instead. Kernels: 1e-13 between eager, jit and a loop
(XLA fuses differently), pairs exactly.
"""

from __future__ import annotations

import copy
import hashlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from evo.core import metrics
from evo.core.trajectory import PosePath3D
from evo.core.units import Unit
from evo.tools import file_interface
from scipy.spatial.transform import Rotation

from jsve.core import ALIGN_METHODS
from jsve.core._geometry import matrix_to_quat
from jsve.core._pose_error import (
    POSE_ALIGN_METHODS,
    RPE_FAILURE_CAUSES,
    align_poses,
    error_statistics,
    pose_errors,
    relative_pose_errors,
    rpe_angle_pairs,
    rpe_pairs,
)
from jsve.core._pose_error_batch import batched_ape, batched_pose_error, batched_rpe, check_delta
from jsve.core._trajectory import batched_run_error, failure_reason

LENGTHS = (40, 95, 2, 61)  # the third is too short to align: failed, not hidden


def pairs(seed: int = 21) -> list[tuple[np.ndarray, np.ndarray]]:
    """(ref, est) [T, 4, 4] of each length: a random walk, and an estimate in another frame and scale."""
    rng = np.random.default_rng(seed)
    out = []
    for n in LENGTHS:
        ref = np.tile(np.eye(4), (n, 1, 1))
        ref[:, :3, :3] = Rotation.from_rotvec(
            np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
        ).as_matrix()
        ref[:, :3, 3] = np.cumsum(rng.normal(scale=0.5, size=(n, 3)), axis=0)
        offset = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        est = ref.copy()
        est[:, :3, :3] = offset @ ref[:, :3, :3]
        est[:, :3, 3] = (
            rng.uniform(0.5, 2.0) * (ref[:, :3, 3] + rng.normal(scale=0.2, size=(n, 3))) @ offset.T
        )
        out.append((ref, est))
    return out


def padded(items):
    n_frames = max(len(r) for r, _ in items)
    ref = np.tile(np.eye(4), (len(items), n_frames, 1, 1))
    est, valid = ref.copy(), np.zeros((len(items), n_frames), bool)
    for i, (r, e) in enumerate(items):
        ref[i, : len(r)], est[i, : len(e)], valid[i, : len(r)] = r, e, True
    return est, ref, valid


@pytest.mark.parametrize("method", ALIGN_METHODS)
@pytest.mark.parametrize("n_first", [None, 30])
def test_equals_run_error_of_one_segment_runs(x64, method, n_first):
    """The one home of per-run evaluation (run_error) scores a run with every pose in one segment the same."""
    est, ref, valid = padded(pairs())
    errors, transforms = batched_pose_error(est, ref, valid, align=method, n_first=n_first)
    as_q = lambda m: matrix_to_quat(jnp.asarray(m[..., :3, :3]))  # noqa: E731
    expected = batched_run_error(
        jnp.asarray(est[..., :3, 3]),
        as_q(est),
        jnp.asarray(valid),
        jnp.zeros(valid.shape, jnp.int32),
        jnp.asarray(ref[..., :3, 3]),
        as_q(ref),
        jnp.asarray(valid),
        jnp.asarray(valid),
        align=method,
        n_first=n_first,
    )
    # Both align and score the same frames with the same functions; only XLA's fusion of the two programs
    # differs, so they agree to a few ulp of the metre-sized errors.
    for got, want in zip(jax.tree.leaves(errors), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=1e-12)
    assert np.asarray(errors.failed).tolist() == [False, False, True, False]
    assert transforms.rotation.shape == (len(LENGTHS), 3, 3)


@pytest.mark.parametrize("method, correct_scale", [("se3", False), ("sim3", True)])
def test_equals_evo_ape(x64, method, correct_scale):
    items = [p for p in pairs(5) if len(p[0]) > 2]
    errors, transforms = batched_pose_error(*padded(items), align=method)
    for i, (ref, est) in enumerate(items):
        ref_path, aligned = PosePath3D(poses_se3=list(ref)), PosePath3D(poses_se3=list(est))
        aligned.align(ref_path, correct_scale=correct_scale)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref_path, copy.deepcopy(aligned)))
        for name, value in ape.get_all_statistics().items():
            # evo and jsve sum in different orders; 1e-6 m is the agreement asked of every APE in jsve.
            got = np.asarray(getattr(errors.stats, name))[i]
            np.testing.assert_allclose(got, value, rtol=1e-9 if name == "sse" else 0, atol=1e-6, err_msg=name)
        assert np.asarray(errors.stats.count)[i] == len(ref) and np.asarray(errors.coverage)[i] == 1.0
    assert not np.asarray(errors.failed).any() and np.asarray(transforms.scale).shape == (len(items),)


def test_shapes_are_checked(unchecked):
    est, ref, valid = padded(pairs()[:1])
    message = r"est and ref must have shape \(R, T, 4, 4\) and valid \(R, T\)"
    with unchecked(), pytest.raises(ValueError, match=message):
        batched_pose_error(est, ref, valid[:, :-1])


@pytest.mark.parametrize("method", ALIGN_METHODS)
def test_a_nan_or_overflowing_pose_fails_its_run_alone(method):
    """Issue 12: a NaN estimate scored 0.000000 m. It fails its run, with the cause named; the other runs
    of the batch keep their numbers (float32: 1e20 m squares to inf)."""
    items = pairs(9)
    est, ref, valid = padded(items)
    clean, _ = batched_pose_error(est.astype(np.float32), ref.astype(np.float32), valid, align=method)
    est[0, 5, 1, 3] = np.nan
    est[3, 7, 0, 3] = 1e20
    errors, _ = batched_pose_error(est.astype(np.float32), ref.astype(np.float32), valid, align=method)
    failure = np.asarray(errors.failure)
    assert np.asarray(errors.failed)[[0, 3]].all()
    assert all("non-finite" in failure_reason(failure[i]) for i in (0, 3))
    assert failure_reason(failure[1]) == "" and float(errors.stats.rmse[1]) == float(clean.stats.rmse[1])


# ----------------------------------------------------------------------------------------------------------
# Every pose relation, APE and RPE, against evo

RELATIONS = {
    "translation": metrics.PoseRelation.translation_part,
    "angle_deg": metrics.PoseRelation.rotation_angle_deg,
    "angle_rad": metrics.PoseRelation.rotation_angle_rad,
    "full": metrics.PoseRelation.full_transformation,
}
UNITS = {"f": Unit.frames, "m": Unit.meters, "d": Unit.degrees, "r": Unit.radians}
REL_TOL = 1e-9  # float64, different summation and product orders (measured <= 5e-12)
ZERO_TOL = 1e-12  # a value 0 in exact arithmetic: rounding noise ~1e-15 on both sides
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")


def noisy_pairs(lengths=(120, 95, 150), seed: int = 3) -> list[tuple[np.ndarray, np.ndarray]]:
    """(ref, est) [T, 4, 4]: a random walk, and an estimate with rotation (0.6 deg) and position (0.1 m)
    noise, expressed in another world frame and scale (so that alignment matters)."""
    rng = np.random.default_rng(seed)
    out = []
    for n in lengths:
        ref = np.tile(np.eye(4), (n, 1, 1))
        ref[:, :3, :3] = Rotation.from_rotvec(
            np.cumsum(rng.normal(scale=0.08, size=(n, 3)), axis=0)
        ).as_matrix()
        ref[:, :3, 3] = np.cumsum(rng.normal(scale=0.5, size=(n, 3)), axis=0)
        offset = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        noise = Rotation.from_rotvec(rng.normal(scale=0.01, size=(n, 3))).as_matrix()
        est = ref.copy()
        est[:, :3, :3] = offset @ ref[:, :3, :3] @ noise
        p = ref[:, :3, 3] + rng.normal(scale=0.1, size=(n, 3))
        est[:, :3, 3] = rng.uniform(0.5, 2.0) * p @ offset.T + rng.normal(size=3)
        out.append((ref, est))
    return out


def evo_aligned(ref: np.ndarray, est: np.ndarray, align: str, n_first: int | None = None):
    """evo's PosePath3Ds after evo_ape's / evo_rpe's alignment step."""
    r, e = PosePath3D(poses_se3=list(ref)), PosePath3D(poses_se3=list(est))
    n = -1 if n_first is None else n_first
    if align in ("se3", "sim3"):
        e.align(r, correct_scale=align == "sim3", n=n)
    elif align == "scale":
        e.align(r, correct_only_scale=True, n=n)
    elif align == "origin":
        e.align_origin(r)
    return r, e


def evo_ape(ref, est, relation, align, n_first=None) -> dict:
    ape = metrics.APE(RELATIONS[relation])
    ape.process_data(evo_aligned(ref, est, align, n_first))
    return ape.get_all_statistics()


def evo_rpe(ref, est, relation, delta, unit, all_pairs, align="none", from_reference=False, rel_tol=0.1):
    rpe = metrics.RPE(RELATIONS[relation], delta, UNITS[unit], rel_tol, all_pairs, from_reference)
    rpe.process_data(evo_aligned(ref, est, align))
    return rpe.get_all_statistics(), rpe


@pytest.fixture(scope="module")
def _evo_pairs_cache() -> dict:
    return {}


@pytest.fixture
def evo_pairs_once(monkeypatch, _evo_pairs_cache):
    """evo's own pair choice (metrics.id_pairs_from_delta, which metrics.RPE.process_data calls) run once per
    poses and options in this module, its answer reused: the four relations of an RPE case choose the same
    pairs on the same poses (evo's all pairs by angle is O(T^2) in Python). evo still scores every relation
    itself."""
    choose = metrics.id_pairs_from_delta

    def once(poses, delta, delta_unit, rel_tol=0.1, all_pairs=False):
        key = (hashlib.sha256(np.stack(poses).tobytes()).hexdigest(), delta, delta_unit, rel_tol, all_pairs)
        if key not in _evo_pairs_cache:
            _evo_pairs_cache[key] = choose(poses, delta, delta_unit, rel_tol, all_pairs)
        return list(_evo_pairs_cache[key])

    monkeypatch.setattr(metrics, "id_pairs_from_delta", once)


def assert_stats(stats, i: int, expected: dict, what: str) -> None:
    for name in STATS:
        got, want = float(np.asarray(getattr(stats, name))[i]), expected[name]
        np.testing.assert_allclose(got, want, rtol=REL_TOL, atol=ZERO_TOL, err_msg=f"{what}: {name}")
        if abs(want) > ZERO_TOL:  # the relative test alone, where the value is not rounding noise
            assert abs(got - want) <= REL_TOL * abs(want), f"{what}: {name} {got} vs {want}"


@pytest.fixture(scope="module")
def kitti00(shared_data):
    """KITTI 00's ground truth and evo's ORB-SLAM estimate of it, [4541, 4, 4] each (rotations written with
    limited digits: not exactly orthogonal, which evo's scipy projects away)."""
    root = shared_data / "kitti"
    ref = np.stack(file_interface.read_kitti_poses_file(root / "odometry_poses" / "00.txt").poses_se3)
    est = np.stack(file_interface.read_kitti_poses_file(root / "orbslam_estimate_00.txt").poses_se3)
    return ref, est


RANDOM_RUNS = 3  # noisy_pairs()'s runs: 0-2 of the APE batch, KITTI 00 the next


@pytest.fixture(scope="module")
def ape_batch(request):
    """noisy_pairs() and, where ../shared/data holds it, KITTI 00 (run RANDOM_RUNS) padded into one batch,
    and the errors of batched_ape of it per (align, n_first, relation), computed once: the random and the
    KITTI APE tests check the same configurations, so one compiled program each (one per configuration and
    shape) serves both."""
    items = noisy_pairs()
    assert len(items) == RANDOM_RUNS
    try:
        items.append(request.getfixturevalue("kitti00"))
    except pytest.skip.Exception:  # no real data: the random runs alone; the KITTI test skips
        pass
    batch, results = padded(items), {}

    def ape(align, n_first, relation):
        key = (align, n_first, relation)
        if key not in results:
            results[key] = batched_ape(*batch, align=align, n_first=n_first, relation=relation).errors
        return results[key]

    return items, ape


@pytest.mark.parametrize("relation", RELATIONS)
@pytest.mark.parametrize(
    ("align", "n_first"),
    [(m, None) for m in POSE_ALIGN_METHODS if m != "posyaw"] + [("se3", 40), ("sim3", 40)],
)
def test_ape_equals_evo_on_random_trajectories(x64, ape_batch, relation, align, n_first):
    items, ape = ape_batch
    errors = ape(align, n_first, relation)
    for i, (ref, est) in enumerate(items[:RANDOM_RUNS]):
        assert_stats(errors.stats, i, evo_ape(ref, est, relation, align, n_first), f"run {i}")
        assert int(errors.stats.count[i]) == len(ref)
    assert not np.asarray(errors.failed)[:RANDOM_RUNS].any()


RPE_CASES = [  # (delta, unit, all_pairs)
    (1, "f", False),
    (7, "f", False),
    (5, "f", True),
    (3.0, "m", False),
    (2.5, "m", True),
    (20.0, "d", False),
    (0.3, "r", False),
    (25.0, "d", True),
    (0.5, "r", True),
]


@pytest.mark.parametrize("relation", RELATIONS)
@pytest.mark.parametrize(("delta", "unit", "all_pairs"), RPE_CASES)
def test_rpe_equals_evo_on_random_trajectories(x64, evo_pairs_once, relation, delta, unit, all_pairs):
    """Runs of three lengths in one padded batch: evo's pairs (the same j of each pair, in evo's order) and
    every statistic."""
    items = noisy_pairs()
    result = batched_rpe(*padded(items), delta=delta, unit=unit, all_pairs=all_pairs, relation=relation)
    for i, (ref, est) in enumerate(items):
        expected, rpe = evo_rpe(ref, est, relation, delta, unit, all_pairs)
        mask = np.asarray(result.mask[i])
        assert np.asarray(result.second[i])[mask].tolist() == rpe.delta_ids, f"run {i}: pairs"
        assert_stats(result.stats, i, expected, f"run {i}")
        assert int(result.stats.count[i]) == len(rpe.error) > 0
    assert not np.asarray(result.failed).any()


@pytest.mark.parametrize(
    ("align", "from_reference"),
    [("sim3", False), ("sim3", True), ("scale", False), ("origin", False), ("se3", False)],
)
@pytest.mark.parametrize(
    ("delta", "unit", "all_pairs"), [(4.0, "m", False), (2.0, "m", True), (15.0, "d", False)]
)
def test_rpe_after_alignment_equals_evo(x64, align, from_reference, delta, unit, all_pairs):
    """evo_rpe aligns first and picks the pairs on the aligned estimate (a scale changes the path), or on
    the reference with --pairs_from_reference."""
    items = noisy_pairs(seed=8)
    result = batched_rpe(
        *padded(items), delta=delta, unit=unit, all_pairs=all_pairs, align=align,
        pairs_from_reference=from_reference,
    )  # fmt: skip
    for i, (ref, est) in enumerate(items):
        expected, rpe = evo_rpe(ref, est, "translation", delta, unit, all_pairs, align, from_reference)
        assert np.asarray(result.second[i])[np.asarray(result.mask[i])].tolist() == rpe.delta_ids
        assert_stats(result.stats, i, expected, f"run {i}")


@pytest.mark.parametrize("relation", RELATIONS)
def test_ape_equals_evo_on_kitti_00(x64, kitti00, ape_batch, relation):
    """KITTI 00 as run RANDOM_RUNS of the random APE tests' batch (padding leaves a run's numbers alone)."""
    ref, est = kitti00
    items, ape = ape_batch
    assert items[RANDOM_RUNS][0] is ref and items[RANDOM_RUNS][1] is est
    aligns = [m for m in POSE_ALIGN_METHODS if m != "posyaw"]
    for align in aligns:
        errors = ape(align, None, relation)
        assert_stats(errors.stats, RANDOM_RUNS, evo_ape(ref, est, relation, align), align)
        assert int(errors.stats.count[RANDOM_RUNS]) == len(ref)


KITTI_RPE_CASES = [  # (delta, unit, all_pairs, poses): evo's all pairs by angle is O(T^2) in Python
    (1, "f", False, None),
    (10, "f", True, None),
    (100.0, "m", False, None),
    (50.0, "m", True, None),
    (10.0, "d", False, None),
    (0.2, "r", False, None),
    (10.0, "d", True, 600),
]


@pytest.mark.parametrize(("delta", "unit", "all_pairs", "poses"), KITTI_RPE_CASES)
def test_rpe_equals_evo_on_kitti_00(x64, kitti00, evo_pairs_once, delta, unit, all_pairs, poses):
    ref, est = (a[:poses] for a in kitti00)
    for relation in RELATIONS:
        result = batched_rpe(
            est[None], ref[None], np.ones((1, len(ref)), bool), delta=delta, unit=unit, all_pairs=all_pairs,
            relation=relation, align="se3",
        )  # fmt: skip
        expected, rpe = evo_rpe(ref, est, relation, delta, unit, all_pairs, align="se3")
        assert np.asarray(result.second[0])[np.asarray(result.mask[0])].tolist() == rpe.delta_ids
        assert_stats(result.stats, 0, expected, relation)


def test_rpe_without_pairs_fails_the_run_with_its_reason(x64):
    """evo raises 'empty index list'; jsve fails that run alone and says why."""
    items = noisy_pairs(lengths=(120, 4))
    result = batched_rpe(*padded(items), delta=10, unit="f")
    assert np.asarray(result.failed).tolist() == [False, True]
    assert failure_reason(result.failure[1], RPE_FAILURE_CAUSES) == "no pose pair at this delta"
    assert int(result.stats.count[1]) == 0 and int(result.stats.count[0]) == 11
    short = batched_rpe(*padded(items), delta=10, unit="f", align="se3")  # 4 poses align: not degenerate
    assert failure_reason(short.failure[1], RPE_FAILURE_CAUSES) == "no pose pair at this delta"
    two = batched_rpe(*padded(noisy_pairs(lengths=(120, 2))), delta=1, unit="f", align="se3")
    assert failure_reason(two.failure[1], RPE_FAILURE_CAUSES) == "degenerate alignment"


@pytest.mark.parametrize(
    ("delta", "unit", "message"),
    [
        (0, "f", "whole number of frames >= 1"),
        (1.5, "f", "whole number of frames >= 1"),
        (0.0, "m", "delta must be positive"),
        (-1.0, "m", "delta must be positive"),
        (181.0, "d", r"within \(0, 180\]"),
        (3.5, "r", r"within \(0, 3.14159\]"),
        (1.0, "s", "unit must be one of"),
    ],
)
def test_bad_deltas_are_refused(delta, unit, message):
    with pytest.raises(ValueError, match=message):
        check_delta(delta, unit)
    with pytest.raises(ValueError, match=message):
        batched_rpe(*padded(noisy_pairs(lengths=(10,))), delta=delta, unit=unit)


# ----------------------------------------------------------------------------------------------------------
# The single-run kernels: eager == jit == vmap (a loop), gradients


def _batch(seed: int = 5):
    items = noisy_pairs(lengths=(80, 80, 80), seed=seed)
    ref = jnp.asarray(np.stack([r for r, _ in items]))
    est = jnp.asarray(np.stack([e for _, e in items]))
    valid = jnp.arange(80)[None, :] < jnp.asarray([80, 61, 47])[:, None]  # prefixes, as padding leaves them
    return est, ref, valid


def _same(a, b, exact: bool = False) -> None:
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        if exact or not jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        else:
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-13, atol=1e-13)


def _check_kernel(fn, *args) -> None:
    """fn over a leading runs axis: jax.jit(fn) == fn (eager) per run, jax.vmap(fn) == the stacked loop."""
    loop = [fn(*(a[i] for a in args)) for i in range(args[0].shape[0])]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *loop)
    _same(jax.vmap(fn)(*args), stacked)
    for i, want in enumerate(loop):
        _same(jax.jit(fn)(*(a[i] for a in args)), want)


@pytest.mark.parametrize("relation", RELATIONS)
def test_pose_and_relative_errors_eager_jit_vmap(x64, relation):
    est, ref, _ = _batch()
    _check_kernel(lambda e, r: pose_errors(e, r, relation), est, ref)
    first = jnp.tile(jnp.arange(0, 70), (3, 1))
    second = first + jnp.asarray([1, 5, 9])[:, None]
    _check_kernel(lambda e, r, i, j: relative_pose_errors(e, r, i, j, relation), est, ref, first, second)


@pytest.mark.parametrize("method", POSE_ALIGN_METHODS)
def test_align_poses_eager_jit_vmap(x64, method):
    est, ref, valid = _batch()
    _check_kernel(lambda e, r, m: align_poses(e, r, m, method=method), est, ref, valid)


@pytest.mark.parametrize(
    ("delta", "unit", "all_pairs"), [c for c in RPE_CASES if not (c[1] in "dr" and c[2])]
)
def test_rpe_pairs_eager_jit_vmap(x64, delta, unit, all_pairs):
    _, ref, valid = _batch()
    _check_kernel(lambda p, m: rpe_pairs(p, m, delta, unit=unit, all_pairs=all_pairs), ref, valid)
    first, second, mask = rpe_pairs(ref[1], valid[1], delta, unit=unit, all_pairs=all_pairs)
    assert np.asarray(mask).any() and int(np.asarray(second)[np.asarray(mask)].max()) < 61  # not on padding


def test_rpe_angle_pairs_eager_jit_vmap(x64):
    _, ref, valid = _batch()
    _check_kernel(lambda p, m: rpe_angle_pairs(p, m, 25.0, degrees=True), ref, valid)
    blocked = rpe_angle_pairs(ref[0], valid[0], 25.0, degrees=True, rows_per_block=7)
    _same(blocked, rpe_angle_pairs(ref[0], valid[0], 25.0, degrees=True), exact=True)
    assert np.asarray(blocked).any()


def test_error_statistics_eager_jit_vmap_and_numpy(x64):
    errors = jnp.asarray(np.random.default_rng(2).gamma(2.0, size=(4, 50)))
    mask = jnp.arange(50)[None, :] < jnp.asarray([50, 33, 1, 0])[:, None]
    _check_kernel(error_statistics, errors, mask)
    stats = error_statistics(errors[1], mask[1])
    e = np.asarray(errors[1, :33])
    want = dict(
        rmse=np.sqrt(np.mean(e**2)),
        mean=e.mean(),
        median=np.median(e),
        std=e.std(),
        min=e.min(),
        max=e.max(),
        sse=np.sum(e**2),
    )
    for name, value in want.items():
        np.testing.assert_allclose(float(getattr(stats, name)), value, rtol=1e-13, err_msg=name)
    assert int(stats.count) == 33 and float(error_statistics(errors[3], mask[3]).rmse) == 0.0


def test_rpe_pairs_refuses_a_valid_mask_that_is_not_a_prefix(x64):
    _, ref, valid = _batch()
    holed = valid[0].at[10].set(False)
    with pytest.raises(Exception, match="valid must be a prefix"):
        jax.block_until_ready(rpe_pairs(ref[0], holed, 1, unit="f"))


@pytest.mark.parametrize("relation", ["translation", "angle_rad", "full"])
def test_relative_pose_errors_gradient_equals_central_differences(x64, relation):
    """d/d(estimated poses) of a weighted sum of RPEs, against central differences (h = 1e-6: truncation
    ~1e-12, rounding ~1e-10 relative to the O(1) derivatives)."""
    est, ref, _ = _batch(seed=11)
    est, ref = est[0, :12], ref[0, :12]
    first, second = jnp.arange(0, 9), jnp.arange(3, 12)
    weights = jnp.asarray(np.random.default_rng(4).uniform(0.5, 1.5, size=9))

    def loss(e):
        return jnp.sum(weights * relative_pose_errors(e, ref, first, second, relation))

    grad = np.asarray(jax.grad(loss)(est))
    assert np.all(np.isfinite(grad))
    h, flat = 1e-6, np.asarray(est).ravel()
    fd = np.zeros_like(flat)
    for k in np.flatnonzero(np.tile(np.r_[np.ones(12), np.zeros(4)], 12)):  # not the constant bottom rows
        bump = np.zeros_like(flat)
        bump[k] = h
        up, down = (jnp.asarray((flat + s * bump).reshape(est.shape)) for s in (1, -1))
        fd[k] = (loss(up) - loss(down)) / (2 * h)
    np.testing.assert_allclose(grad.ravel(), fd, rtol=1e-6, atol=1e-7)
