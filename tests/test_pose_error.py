"""jsve.core._pose_error: APE of many padded pose pairs, equal to run_error of one-segment runs and to evo."""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from evo.core import metrics
from evo.core.trajectory import PosePath3D
from scipy.spatial.transform import Rotation

from jsve.core import ALIGN_METHODS
from jsve.core._geometry import matrix_to_quat
from jsve.core._pose_error import batched_pose_error
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
