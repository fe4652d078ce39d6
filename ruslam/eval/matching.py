"""Local-feature metrics on one homography pair (SuperPoint / HF-Net protocol), and their averages.

Protocol, in order: cap each image's keypoints to the ``max_keypoints`` best scores over the WHOLE image; then
keep only the keypoints whose warp by H (or H^-1) falls inside the other image (the shared view); match those
by mutual nearest neighbour (L2 for float descriptors, Hamming for packed binary ones); a match is correct at
threshold t when ``|H kp1 - kp2| <= t`` pixels, measured in image 2.

- repeatability (eps = 3 px): (kp1 with a warped kp2 within eps + kp2 with a warped kp1 within eps) / (N1 + N2);
- matching score: correct matches at eps / mean(N1, N2) (N = shared-view keypoints);
- MMA at t: correct matches at t / matches, for t = 1..10 px.

A pair where nothing is detected or matched scores 0 (an extractor that finds nothing has failed, it is not
excused). Averages are plain means over pairs. Pixel centres are at integer coordinates, so an image of width W
spans x in [-0.5, W - 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ruslam.models.feature_matching import descriptor_distances

THRESHOLDS = tuple(range(1, 11))
ROTATION_BINS = ((0.0, 30.0), (30.0, 90.0), (90.0, 180.0))


def warp_points(points: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to points [N, 2] (x, y) -> [N, 2]."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    homog = np.concatenate([pts, np.ones((len(pts), 1))], axis=1) @ np.asarray(H, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return homog[:, :2] / homog[:, 2:3]


def inside_image(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Mask of points [N, 2] inside an image of shape (H, W) (pixel centres at integers)."""
    h, w = shape[:2]
    x, y = points[:, 0], points[:, 1]
    return (x >= -0.5) & (x < w - 0.5) & (y >= -0.5) & (y < h - 0.5)


def cap_keypoints(features: dict, max_keypoints: int) -> dict:
    """Keep the ``max_keypoints`` highest-scoring keypoints of the whole image (stable on ties)."""
    n = len(features["keypoints"])
    if not max_keypoints or n <= max_keypoints:
        return features
    keep = np.sort(np.argsort(-np.asarray(features["scores"]), kind="stable")[:max_keypoints])
    return {k: (np.asarray(v)[keep] if k in ("keypoints", "scores", "descriptors") else v) for k, v in features.items()}


def mutual_nearest_neighbours(desc1: np.ndarray, desc2: np.ndarray, binary: bool) -> np.ndarray:
    """Index pairs [M, 2] (i in desc1, j in desc2) that are each other's nearest neighbour (Hamming for packed
    binary descriptors, L2 for float ones: the SLAM's `descriptor_distances`, one matrix product)."""
    if len(desc1) == 0 or len(desc2) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    dist = descriptor_distances(np.asarray(desc1), np.asarray(desc2), binary)
    nn12 = dist.argmin(axis=1)
    nn21 = dist.argmin(axis=0)
    idx1 = np.arange(len(nn12))
    mutual = nn21[nn12] == idx1
    return np.stack([idx1[mutual], nn12[mutual]], axis=1).astype(np.int64)


@dataclass
class PairResult:
    """Metrics of one pair plus what a match picture needs (shared-view keypoints, matches, their errors)."""

    repeatability: float
    matching_score: float
    mma: np.ndarray  # one value per threshold
    num_keypoints: tuple[int, int]  # shared-view keypoints in image 1 and image 2
    num_matches: int
    keypoints1: np.ndarray = field(repr=False)
    keypoints2: np.ndarray = field(repr=False)
    matches: np.ndarray = field(repr=False)  # [M, 2] indices into keypoints1 / keypoints2
    match_errors: np.ndarray = field(repr=False)  # [M] |H kp1 - kp2| in pixels of image 2


def evaluate_pair(
    features1: dict,
    features2: dict,
    H: np.ndarray,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
    binary: bool,
    max_keypoints: int = 2000,
    eps: float = 3.0,
    thresholds: tuple = THRESHOLDS,
    max_keypoints1: int | None = None,
) -> PairResult:
    """Repeatability, matching score and MMA of one pair; H maps image-1 pixels to image-2 pixels.

    ``max_keypoints1``: another cap for image 1 (0: none), e.g. a reference pooled over several rotations.
    """
    H = np.asarray(H, dtype=np.float64)
    cap1 = max_keypoints if max_keypoints1 is None else max_keypoints1
    f1, f2 = cap_keypoints(features1, cap1), cap_keypoints(features2, max_keypoints)
    kp1 = np.asarray(f1["keypoints"], dtype=np.float64).reshape(-1, 2)
    kp2 = np.asarray(f2["keypoints"], dtype=np.float64).reshape(-1, 2)
    warped1 = warp_points(kp1, H)
    warped2 = warp_points(kp2, np.linalg.inv(H))
    keep1, keep2 = inside_image(warped1, shape2), inside_image(warped2, shape1)
    kp1, warped1, desc1 = kp1[keep1], warped1[keep1], np.asarray(f1["descriptors"])[keep1]
    kp2, desc2 = kp2[keep2], np.asarray(f2["descriptors"])[keep2]
    n1, n2 = len(kp1), len(kp2)

    repeatability = 0.0
    if n1 and n2:  # exact nearest-neighbour distances in image 2 (a k-d tree, not a dense matrix)
        repeated = (cKDTree(kp2).query(warped1)[0] <= eps).sum() + (cKDTree(warped1).query(kp2)[0] <= eps).sum()
        repeatability = float(repeated) / (n1 + n2)

    matches = mutual_nearest_neighbours(desc1, desc2, binary)
    errors = np.linalg.norm(warped1[matches[:, 0]] - kp2[matches[:, 1]], axis=-1) if len(matches) else np.zeros(0)
    mma = np.array([(errors <= t).mean() if len(errors) else 0.0 for t in thresholds])
    matching_score = float((errors <= eps).sum() / ((n1 + n2) / 2)) if n1 + n2 else 0.0
    return PairResult(repeatability, matching_score, mma, (n1, n2), len(matches), kp1, kp2, matches, errors)


def rotation_bin(angle_deg: float, bins: tuple = ROTATION_BINS) -> int:
    """Index of the bin holding |angle| (the last bin includes its upper edge), or -1 when outside all bins."""
    a = abs(float(angle_deg))
    for i, (lo, hi) in enumerate(bins):
        if lo <= a < hi or (i == len(bins) - 1 and a == hi):
            return i
    return -1


def summarize(results: list[PairResult], thresholds: tuple = THRESHOLDS, headline: float = 3.0) -> dict:
    """Means over pairs, in percent: rep, ms, mma (headline threshold), mma_curve, keypoints, matches."""
    if not results:
        return {"pairs": 0}
    curve = np.mean([r.mma for r in results], axis=0) * 100
    return {
        "pairs": len(results),
        "rep": float(np.mean([r.repeatability for r in results]) * 100),
        "ms": float(np.mean([r.matching_score for r in results]) * 100),
        "mma": float(curve[list(thresholds).index(headline)]),
        "mma_curve": curve.tolist(),
        "keypoints": float(np.mean([np.mean(r.num_keypoints) for r in results])),
        "matches": float(np.mean([r.num_matches for r in results])),
    }
