"""The matching step of triangulation (one keyframe against one neighbour), three ways in one process on the same
data: an epipolar distance matrix, then the masked dense search; `epipolar_mask` (normalised lines), then the same
dense search; and `match_knn_ratio` as the SLAM runs it (binary descriptors: only the pairs inside the band scored;
float: the dense search). One BLAS thread, as in the SLAM (`slam.blas_threads`).

    nice .venv/bin/python bench/triangulation_matching.py [--keypoints 700 1000 2000] [--reps 20]

Two views of a synthetic cloud (640x480, 0.3 m baseline at 4-8 m); descriptors are random per point with small
per-view noise, as ORB (256 bits) and XFeat (64 floats). All three must return the same matches.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from ruslam.models.feature_matching import descriptor_distances, match_knn_ratio
from ruslam.slam.geometry import epipolar_mask, fundamental_from_poses, pose_matrix, project

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def distance_matrix_match(d1, d2, x1, x2, F, binary, max_distance, ratio=0.8, px=4.0):
    """An epipolar distance matrix, then the masked dense search."""
    lines = np.c_[x1, np.ones(len(x1))] @ F.T
    dist = np.abs(lines[:, :2] @ x2.T + lines[:, 2:3]) / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    return masked_dense_search(descriptor_distances(d1, d2, binary), dist < px, max_distance, ratio)


def dense_match(d1, d2, x1, x2, F, binary, max_distance, ratio=0.8, px=4.0):
    """Every pair scored, then the mask applied (what `match_knn_ratio` does for float)."""
    return masked_dense_search(descriptor_distances(d1, d2, binary), epipolar_mask(F, x1, x2, px), max_distance, ratio)


def masked_dense_search(d, mask, max_distance, ratio):
    """Mutual 2-NN ratio search over a dense distance matrix with the pairs outside `mask` removed."""
    np.putmask(d, ~mask, np.inf)
    rows = np.arange(len(d))
    best = np.argmin(d, axis=1)
    b1 = d[rows, best]
    keep = (b1 <= max_distance) & (np.argmin(d, axis=0)[best] == rows)
    d[rows, best] = np.inf
    keep &= b1 < ratio * d.min(axis=1)
    i = np.nonzero(keep)[0]
    return i, best[i]


def library_match(d1, d2, x1, x2, F, binary, max_distance, ratio=0.8, px=4.0):
    return match_knn_ratio(d1, d2, binary, max_distance, ratio, mask=epipolar_mask(F, x1, x2, px))


def views(n, binary, rng):
    X = rng.uniform([-3, -2, 4], [3, 2, 8], (n, 3))
    T2 = pose_matrix(np.eye(3), [-0.3, 0.02, 0.05])
    x1, _ = project(K, np.eye(4), X)
    x2, _ = project(K, T2, X)
    x2 += rng.normal(0, 0.7, x2.shape)
    perm = rng.permutation(n)  # the second view lists its keypoints in another order
    if binary:
        d = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        flip = rng.random((n, 256)) < 0.08
        d2 = d ^ np.packbits(flip, axis=1)
        return d, d2[perm], x1, x2[perm], fundamental_from_poses(K, K, T2), 64.0
    d = rng.normal(size=(n, 64)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d2 = d + rng.normal(0, 0.03, d.shape).astype(np.float32)
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    return d, d2[perm], x1, x2[perm], fundamental_from_poses(K, K, T2), 0.5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keypoints", type=int, nargs="+", default=[700, 1000, 2000])
    ap.add_argument("--reps", type=int, default=20)
    args = ap.parse_args()
    threadpool_limits(1, user_api="blas")
    rng = np.random.default_rng(0)
    methods = {"distance matrix": distance_matrix_match, "dense, then mask": dense_match,
               "match_knn_ratio": library_match}
    print(f"median ms of {args.reps} alternating runs; speedup against the distance matrix; same = identical matches")
    print("descriptors  keypoints  " + "  ".join(f"{m:>16s}" for m in methods) + "  speedup  matches  same")
    for binary in (True, False):
        for n in args.keypoints:
            data = views(n, binary, rng)
            times = {m: [] for m in methods}
            for _ in range(args.reps):
                for m, fn in methods.items():
                    t = time.perf_counter()
                    fn(*data[:5], binary, data[5])
                    times[m].append(time.perf_counter() - t)
            outs = [fn(*data[:5], binary, data[5]) for fn in methods.values()]
            same = all(np.array_equal(o[0], outs[0][0]) and np.array_equal(o[1], outs[0][1]) for o in outs)
            ms = {m: 1e3 * float(np.median(t)) for m, t in times.items()}
            print(f"{'ORB 256 bit' if binary else 'float 64':11s}  {n:9d}  "
                  + "  ".join(f"{ms[m]:16.1f}" for m in methods)
                  + f"  {ms['distance matrix'] / ms['match_knn_ratio']:6.1f}x  {len(outs[1][0]):7d}  {same}")


if __name__ == "__main__":
    main()
