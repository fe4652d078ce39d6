"""evo-based APE/RPE: invariance to the aligned transform and hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ruslam.data.readers import Trajectory
from ruslam.eval.trajectory import evaluate_trajectory


def _helix(n=120):
    s = np.linspace(0, 3 * np.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.column_stack([2 * np.cos(s), 1.5 * np.sin(s), 0.3 * s])
    poses[:, :3, :3] = Rotation.from_euler("zyx", np.column_stack([s, 0.2 * np.sin(s), 0.1 * s])).as_matrix()
    return Trajectory(np.arange(n) * 0.1, poses)


def _transform(traj, scale, rotvec, t):
    S = np.eye(4)
    S[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    S[:3, 3] = t
    poses = traj.poses.copy()
    poses[:, :3, 3] *= scale
    return Trajectory(traj.timestamps, S @ poses)


def test_sim3_and_se3_transforms_of_the_ground_truth_give_zero_error():
    ref = _helix()
    sim = _transform(ref, 2.5, [0.3, -0.2, 1.0], [5.0, -1.0, 2.0])
    out = evaluate_trajectory(sim, ref, alignment="sim3")
    assert out.ape_rmse < 1e-9 and out.rpe_rmse < 1e-9 and out.scale == pytest.approx(0.4)
    assert out.matched == 120
    se3 = _transform(ref, 1.0, [0.3, -0.2, 1.0], [5.0, -1.0, 2.0])
    assert evaluate_trajectory(se3, ref, alignment="se3").ape_rmse < 1e-9
    assert evaluate_trajectory(sim, ref, alignment="se3").ape_rmse > 0.5  # SE3 cannot undo a scale
    assert evaluate_trajectory(se3, ref, alignment="none").ape_rmse > 1.0


def test_ape_equals_hand_computed_value_with_noise():
    """Each position appears twice with offsets +d and -d: the noise is uncorrelated with the path, so the SE3
    alignment is the identity (APE = d) and Sim3 shrinks by s = var/(var + d^2)."""
    base = _helix(60)
    d, offset = 0.05, np.array([0.6, 0.0, 0.8])  # |offset| = 1
    poses = np.repeat(base.poses, 2, axis=0)
    ref = Trajectory(np.arange(120) * 0.1, poses)
    noisy = poses.copy()
    noisy[:, :3, 3] += d * offset * np.where(np.arange(120) % 2 == 0, 1, -1)[:, None]
    est = Trajectory(ref.timestamps, noisy)
    assert evaluate_trajectory(est, ref, alignment="se3").ape_rmse == pytest.approx(d, rel=1e-9)
    centred = ref.positions - ref.positions.mean(axis=0)
    var = (centred**2).sum(axis=1).mean()
    s = var / (var + d * d)
    expected = np.sqrt((s - 1) ** 2 * var + s * s * d * d)
    out = evaluate_trajectory(est, ref, alignment="sim3")
    assert out.scale == pytest.approx(s, rel=1e-9) and out.ape_rmse == pytest.approx(expected, rel=1e-9)


def test_rpe_uses_a_tenth_of_a_metre_and_measures_scale_drift():
    """Straight line at 1/32 m per frame (exact in binary): consecutive pairs are the first 4 frames >= 0.1 m
    apart (0.125 m); the estimate travels 10% too far, so every pair is 12.5 mm off."""
    n = 50
    ref_poses = np.tile(np.eye(4), (n, 1, 1))
    ref_poses[:, 0, 3] = np.arange(n) / 32
    est_poses = ref_poses.copy()
    est_poses[:, 0, 3] *= 1.1
    out = evaluate_trajectory(Trajectory(np.arange(n) * 0.1, est_poses), Trajectory(np.arange(n) * 0.1, ref_poses),
                              alignment="none")
    assert out.rpe_rmse == pytest.approx(0.0125, rel=1e-9)


def test_rpe_is_nan_when_the_path_is_shorter_than_its_delta():
    """A 5 cm path has no pair of poses 0.1 m apart: APE is still computed, RPE is reported as n/a (NaN)."""
    n = 20
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * 0.0025
    poses[:, 1, 3] = np.sin(np.arange(n)) * 0.001
    out = evaluate_trajectory(Trajectory(np.arange(n) * 0.1, poses), Trajectory(np.arange(n) * 0.1, poses))
    assert np.isnan(out.rpe_rmse) and out.ape_rmse < 1e-9


def test_association_by_timestamp_and_clear_errors():
    ref = _helix()
    part = Trajectory(ref.timestamps[10:50] + 0.004, ref.poses[10:50])  # 4 ms clock offset, subset of frames
    out = evaluate_trajectory(part, ref)
    assert out.matched == 40 and out.ape_rmse < 1e-9
    with pytest.raises(ValueError, match="No estimated pose lies within"):
        evaluate_trajectory(Trajectory(ref.timestamps + 100, ref.poses), ref)
    with pytest.raises(ValueError, match="at least 3 poses"):
        evaluate_trajectory(Trajectory(ref.timestamps[:2], ref.poses[:2]), ref)
    bad = ref.poses.copy()
    bad[5, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        evaluate_trajectory(Trajectory(ref.timestamps, bad), ref)
    with pytest.raises(ValueError, match="alignment"):
        evaluate_trajectory(ref, ref, alignment="affine")
