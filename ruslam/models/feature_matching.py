"""Descriptor matching: kNN + ratio test (optionally mutual) and window search around projected points.

Distances are Hamming bit counts for packed binary descriptors (ORB) and Euclidean for float descriptors; the
dense case is one matrix product, the window case only scores the keypoint/point pairs that fall in a window
(found with a k-d tree), so it costs O(pairs) instead of O(points x keypoints).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def descriptor_distances(a: np.ndarray, b: np.ndarray, binary: bool) -> np.ndarray:
    """All pairwise distances [Na, Nb] (float32) between descriptor sets."""
    if binary:
        if len(a) * len(b) <= 400:  # a map point's few observations: XOR + popcount beats unpacking bits (3x)
            return np.bitwise_count(a[:, None] ^ b[None]).sum(-1, dtype=np.int32).astype(np.float32)
        # bits as +-1: a.b = bits - 2 * hamming, one product and two in-place passes (exact integers in float32;
        # 2.4x faster than |a| + |b| - 2 a.b over 0/1 bits, whose temporaries cost more than the product)
        sa = np.unpackbits(a, axis=1).astype(np.float32) * 2.0 - 1.0
        sb = np.unpackbits(b, axis=1).astype(np.float32) * 2.0 - 1.0
        d = sa @ sb.T
        d *= -0.5
        d += 0.5 * sa.shape[1]
        return d
    a = a.astype(np.float32, copy=False)
    b = b.astype(np.float32, copy=False)
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2.0 * a @ b.T
    return np.sqrt(np.maximum(d2, 0.0))


def paired_distances(a: np.ndarray, b: np.ndarray, binary: bool) -> np.ndarray:
    """Row-wise distances between two equally long descriptor sets [P, D] -> [P]."""
    if binary:
        return np.bitwise_count(np.bitwise_xor(a, b)).sum(1).astype(np.float32)
    diff = a.astype(np.float32, copy=False) - b.astype(np.float32, copy=False)
    return np.sqrt((diff * diff).sum(1))


def match_knn_ratio(
    desc1: np.ndarray, desc2: np.ndarray, binary: bool, max_distance: float, ratio: float = 0.8,
    mutual: bool = True, mask: np.ndarray | None = None, distances: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i1, i2) of matches desc1[i1] <-> desc2[i2]: 2-NN ratio test, distance gate, optional mutual NN.

    `mask` [N1, N2] (bool) restricts the allowed pairs (e.g. an epipolar constraint). Binary descriptors are then
    scored on the masked pairs only (`_match_masked_binary`: the same matches, ~2 % of the pairs in an epipolar
    band); float ones on all pairs (scoring only the masked pairs was slower, bench/triangulation_matching.py).
    `distances`: their `descriptor_distances`, when already computed (overwritten).
    """
    empty = (np.zeros(0, int), np.zeros(0, int))
    if len(desc1) == 0 or len(desc2) == 0:
        return empty
    if binary and mask is not None:
        return _match_masked_binary(desc1, desc2, max_distance, ratio, mutual, mask)
    d = descriptor_distances(desc1, desc2, binary) if distances is None else distances
    if mask is not None:
        np.putmask(d, ~mask, np.inf)
    rows = np.arange(len(d))
    best = np.argmin(d, axis=1)  # two argmin passes: several times cheaper than argpartition on N1 x N2
    d1 = d[rows, best]
    keep = d1 <= max_distance
    if mutual:
        keep &= np.argmin(d, axis=0)[best] == rows
    if d.shape[1] >= 2:
        d[rows, best] = np.inf
        keep &= d1 < ratio * d.min(axis=1)
    i1 = np.nonzero(keep)[0]
    return i1, best[i1]


def _match_masked_binary(desc1, desc2, max_distance, ratio, mutual, mask) -> tuple[np.ndarray, np.ndarray]:
    """`match_knn_ratio` on the masked pairs only, with its ties: among equal distances the lowest index wins.
    Distances are integers (0-256 bits), so one integer key per sort orders by (row, distance, column)."""
    flat = np.flatnonzero(mask)
    i, j = np.divmod(flat, mask.shape[1])
    d = paired_distances(desc1[i], desc2[j], True).astype(np.int64)
    by_row = np.argsort(i * 257 + d, kind="stable")  # pairs come by (row, column): the stable sort keeps columns up
    i, j, d = i[by_row], j[by_row], d[by_row]
    first = np.ones(len(i), bool)
    first[1:] = i[1:] != i[:-1]
    starts = np.nonzero(first)[0]
    rows, best, d1 = i[starts], j[starts], d[starts]
    second = np.full(len(starts), np.inf)
    has_second = np.append(starts[1:], len(i)) - starts > 1
    second[has_second] = d[starts[has_second] + 1]
    keep = (d1 <= max_distance) & (d1 < ratio * second)
    if mutual:
        by_col = np.argsort((j * 257 + d) * mask.shape[0] + i)  # per column: best distance, then the lowest row
        col_first = np.ones(len(by_col), bool)
        col_first[1:] = j[by_col][1:] != j[by_col][:-1]
        col_best_row = np.full(mask.shape[1], -1)
        col_best_row[j[by_col][col_first]] = i[by_col][col_first]
        keep &= col_best_row[best] == rows
    return rows[keep], best[keep]


def match_in_windows(
    uv: np.ndarray, point_desc: np.ndarray, keypoints: np.ndarray, kp_desc: np.ndarray, radius,
    binary: bool, max_distance: float, ratio: float = 0.9, available: np.ndarray | None = None,
    distinct_px: float = 0.0, rival_radius: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Match projected points uv [M, 2] to keypoints [N, 2] inside a window of `radius` pixels (scalar or [M]).

    Best candidate per point by descriptor distance, gated by `max_distance` and a ratio test against the best
    candidate within `rival_radius` (default: the window) that lies more than `distinct_px` from it (keypoints
    closer than the measurement noise are one image location: a dense detector's neighbours share its descriptor,
    and a ratio test against them rejects the right match); each keypoint is given to at most one point (the
    closest in descriptor space). `available` [N] bool masks keypoints already matched. Returns (point indices,
    keypoint indices).
    """
    empty = (np.zeros(0, int), np.zeros(0, int))
    if len(uv) == 0 or len(keypoints) == 0:
        return empty
    radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(uv),))
    reach = radius if rival_radius is None else np.maximum(radius, rival_radius)
    kp_tree = cKDTree(keypoints)
    pairs = cKDTree(uv).sparse_distance_matrix(kp_tree, float(reach.max()), output_type="ndarray")
    ip, ik, dist_px = pairs["i"].astype(int), pairs["j"].astype(int), pairs["v"]
    keep = dist_px <= reach[ip]
    if available is not None:
        keep &= available[ik]
    ip, ik, dist_px = ip[keep], ik[keep], dist_px[keep]
    if len(ip) == 0:
        return empty
    dd = paired_distances(point_desc[ip], kp_desc[ik], binary)
    inside = dist_px <= radius[ip]
    order = np.lexsort((dd, ~inside, ip))  # by point, the window's candidates first, then by descriptor distance
    ip, ik, dd, inside = ip[order], ik[order], dd[order], inside[order]
    first = np.ones(len(ip), bool)
    first[1:] = ip[1:] != ip[:-1]
    starts = np.nonzero(first)[0]
    best_ip, best_ik, best_d = ip[starts], ik[starts], dd[starts]
    group = np.cumsum(first) - 1
    rival = ~first  # candidates other than the best, and (distinct_px) away from it
    if distinct_px > 0:
        rival &= np.sum((keypoints[ik] - keypoints[best_ik[group]]) ** 2, 1) > distinct_px**2
    second_d = np.full(len(starts), np.inf, dtype=np.float32)
    np.minimum.at(second_d, group[rival], dd[rival])
    ok = inside[starts] & (best_d <= max_distance) & (best_d < ratio * second_d)
    best_ip, best_ik, best_d = best_ip[ok], best_ik[ok], best_d[ok]
    order = np.argsort(best_d, kind="stable")  # one point per keypoint: the closest descriptor wins
    _, unique = np.unique(best_ik[order], return_index=True)
    sel = np.sort(order[unique])
    return best_ip[sel], best_ik[sel]
