"""Local BA cost: `ruslam.slam.optimization.bundle_adjustment` against the same gtsam problem with the held
keyframes as NonlinearEquality factors (what it used before), in one process.

    nice .venv/bin/python bench/bundle_adjustment.py [--poses 12] [--points 3000] [--views 5] [--reps 3]

The problem is the size of one local BA of the SLAM at 2,000 keypoints (7 optimised + 5 held keyframes, ~15k
Huber projection factors). gtsam eliminates NonlinearEquality's constrained noise model by QR instead of Cholesky,
which slows the whole solve; tight priors keep the held poses in place (to ~1e-6) at Cholesky speed.
"""

from __future__ import annotations

import argparse
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from ruslam.slam.map import inverse_pose
from ruslam.slam.optimization import HUBER_DELTA, _cal, _pose3, bundle_adjustment


def problem(num_poses: int, num_points: int, views: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    K = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    poses = np.stack([np.eye(4)] * num_poses)
    poses[:, 0, 3] = -0.1 * np.arange(num_poses)
    points = np.c_[rng.uniform(-3, 3, num_points), rng.uniform(-2, 2, num_points), rng.uniform(4, 8, num_points)]
    oi = np.concatenate([rng.choice(num_poses, views, replace=False) for _ in range(num_points)])
    oj = np.repeat(np.arange(num_points), views)
    Xc = np.einsum("nij,nj->ni", poses[oi, :3, :3], points[oj]) + poses[oi, :3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2] + rng.normal(0, 1, (len(oi), 2))
    noisy = poses.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.01, (num_poses, 3))
    return K, noisy, points + rng.normal(0, 0.05, points.shape), oi, oj, uv


def with_equality(K, poses, fixed, points, oi, oj, uv, iterations):
    """The previous formulation: held poses as NonlinearEqualityPose3, same factors and LM stages (no outlier
    step between the stages, which only favours it)."""
    cal = _cal(K)
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(HUBER_DELTA),
                                           gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    values = gtsam.Values()
    for i, T in enumerate(poses):
        values.insert(X(i), _pose3(inverse_pose(T)))
    for j, p in enumerate(points):
        values.insert(L(j), p)
    for iters in iterations:
        graph = gtsam.NonlinearFactorGraph()
        for i in np.nonzero(fixed)[0]:
            graph.add(gtsam.NonlinearEqualityPose3(X(int(i)), values.atPose3(X(int(i)))))
        for i, j, z in zip(oi, oj, uv, strict=True):
            graph.add(gtsam.GenericProjectionFactorCal3_S2(z, noise, X(int(i)), L(int(j)), cal))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iters)
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return graph.error(values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--poses", type=int, default=12)
    parser.add_argument("--held", type=int, default=5)
    parser.add_argument("--points", type=int, default=3000)
    parser.add_argument("--views", type=int, default=5)
    parser.add_argument("--reps", type=int, default=3)
    args = parser.parse_args()
    K, poses, points, oi, oj, uv = problem(args.poses, args.points, args.views)
    fixed = np.arange(args.poses) >= args.poses - args.held
    times = {"NonlinearEquality (before)": [], "priors (bundle_adjustment)": []}
    for _ in range(args.reps):  # round-robin so that load changes hit both alike
        start = time.perf_counter()
        with_equality(K, poses, fixed, points, oi, oj, uv, (3, 4))
        times["NonlinearEquality (before)"].append(time.perf_counter() - start)
        start = time.perf_counter()
        out_poses, _, inliers = bundle_adjustment(poses, fixed, points, oi, oj, uv, K, iterations=(3, 4))
        times["priors (bundle_adjustment)"].append(time.perf_counter() - start)
    assert np.allclose(out_poses[fixed], poses[fixed]), "held poses moved"
    print(f"{args.poses} poses ({args.held} held), {args.points} points, {len(oi)} observations, "
          f"{inliers.mean():.1%} inliers, median of {args.reps}")
    base = np.median(times["NonlinearEquality (before)"])
    for name, t in times.items():
        print(f"{name:28s} {1e3 * np.median(t):8.0f} ms  {base / np.median(t):5.1f}x")


if __name__ == "__main__":
    main()
