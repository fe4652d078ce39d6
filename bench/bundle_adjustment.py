"""Local BA cost: the numpy Schur-complement solver against gtsam on the same problem, in one process.

    nice .venv/bin/python bench/bundle_adjustment.py [--poses 12] [--points 3000] [--views 5] [--reps 3]

The problem is the size of one local BA of the SLAM at 2,000 keypoints (7 optimised + 5 held keyframes, ~15k
Huber projection factors, 5 % of the observations gross outliers). Both solvers run ORB-SLAM's two passes
(iterations 3 and 4, outliers dropped in between); the bench prints each one's time, the final reprojection RMSE
over the inliers and how far the two solutions are apart.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ruslam.slam.bundle_adjustment import SOLVERS, bundle_adjustment, observation_chi2


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
    wrong = rng.random(len(oi)) < 0.05
    uv[wrong] += rng.uniform(-40, 40, (wrong.sum(), 2))
    noisy = poses.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.01, (num_poses, 3))
    return K, noisy, points + rng.normal(0, 0.05, points.shape), oi, oj, uv


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
    times = {s: [] for s in SOLVERS}
    out = {}
    for _ in range(args.reps):  # round-robin so that load changes hit both alike
        for solver in SOLVERS:
            start = time.perf_counter()
            out[solver] = bundle_adjustment(poses, fixed, points, oi, oj, uv, K, iterations=(3, 4), solver=solver)
            times[solver].append(time.perf_counter() - start)
    print(f"{args.poses} poses ({args.held} held), {args.points} points, {len(oi)} observations, median of "
          f"{args.reps}")
    base = np.median(times["gtsam"])
    for solver in SOLVERS:
        T, X, inl = out[solver]
        o = np.argsort(oi, kind="stable")  # observation_chi2 takes observations sorted by pose
        rmse = np.sqrt(np.mean(observation_chi2(T, X, (oi[o], oj[o], uv[o], np.zeros(len(oi), bool)), K)[inl[o]]))
        print(f"{solver:6s} {1e3 * np.median(times[solver]):8.0f} ms  {base / np.median(times[solver]):5.1f}x  "
              f"inliers {inl.mean():.1%}  RMSE {rmse:.3f} px")
    (Ta, Xa, _), (Tb, Xb, _) = out["schur"], out["gtsam"]
    print(f"schur vs gtsam: max pose translation difference {np.abs(Ta[:, :3, 3] - Tb[:, :3, 3]).max():.2e} m, "
          f"max point difference {np.abs(Xa - Xb).max():.2e} m")


if __name__ == "__main__":
    main()
