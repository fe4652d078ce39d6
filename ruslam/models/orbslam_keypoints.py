"""Keypoints as ORB-SLAM's ORBextractor chooses them (Mur-Artal et al.; ORB_SLAM3 src/ORBextractor.cc).

Plain ``cv2.ORB`` keeps the strongest FAST corners of the whole image at one threshold (20): a weakly textured or
turbid frame gives ~100 keypoints, bunched on the few strong edges. ORB-SLAM instead, on every level of an
8-level pyramid (scale 1.2):

1. gives the level a share of the budget decreasing geometrically with the scale (the last level the remainder);
2. detects FAST over a grid of ~35 px cells, with the initial threshold (20) and, in cells that found nothing,
   the minimum one (7), so faint texture still yields corners where there is nothing better;
3. spreads the level's share over the image with a quadtree: nodes holding more than one corner are split in four
   until there are as many nodes as the share, then each node keeps its strongest corner;
4. orients each corner by its intensity centroid (radius 15) for the rotated BRIEF descriptor.

Step 2 is done here with one FAST pass per level at the minimum threshold: FAST's score of a corner does not depend
on the threshold, and non-maximum suppression at threshold 20 keeps exactly the corners of the threshold-7 pass whose
score is >= 20 (a neighbour that could suppress such a corner scores higher, so it passes both thresholds). A cell
then keeps its corners scoring >= 20, or all of them when it has none.
"""

from __future__ import annotations

from operator import attrgetter

import cv2
import numpy as np

PATCH_SIZE = 31  # rBRIEF patch (OpenCV and ORB-SLAM)
HALF_PATCH = 15  # radius of the intensity-centroid disc
EDGE = 19  # no keypoint closer than this to a level's border (ORB-SLAM's EDGE_THRESHOLD)


def level_shares(total: int, levels: int, scale_factor: float) -> list[int]:
    """Keypoints wanted per level: a geometric series in 1/scale_factor summing to ``total``."""
    factor = 1.0 / scale_factor
    first = total * (1 - factor) / (1 - factor**levels)
    shares = [int(round(first * factor**k)) for k in range(levels - 1)]
    return shares + [max(total - sum(shares), 0)]


def pyramid(gray: np.ndarray, levels: int, scale_factor: float) -> list[np.ndarray]:
    out = [gray]
    for k in range(1, levels):
        w, h = round(gray.shape[1] / scale_factor**k), round(gray.shape[0] / scale_factor**k)
        if min(w, h) <= 2 * EDGE + 2:
            break
        out.append(cv2.resize(out[-1], (w, h), interpolation=cv2.INTER_LINEAR))
    return out


def grid_fast(image: np.ndarray, ini_threshold: int, min_threshold: int, cell: int = 35):
    """FAST corners (x, y, score) inside the level's border, adaptive threshold per grid cell."""
    fast = cv2.FastFeatureDetector_create(threshold=int(min_threshold), nonmaxSuppression=True)
    kps = fast.detect(image)
    if not kps:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    xy = cv2.KeyPoint_convert(kps).reshape(-1, 2)
    score = np.fromiter(map(attrgetter("response"), kps), np.float32, len(kps))  # 1.2x a generator
    h, w = image.shape[:2]
    inside = (xy[:, 0] >= EDGE) & (xy[:, 0] < w - EDGE) & (xy[:, 1] >= EDGE) & (xy[:, 1] < h - EDGE)
    xy, score = xy[inside], score[inside]
    cols, rows = max(1, (w - 2 * EDGE) // cell), max(1, (h - 2 * EDGE) // cell)
    cx = np.minimum(((xy[:, 0] - EDGE) * cols / (w - 2 * EDGE)).astype(int), cols - 1)
    cy = np.minimum(((xy[:, 1] - EDGE) * rows / (h - 2 * EDGE)).astype(int), rows - 1)
    cell_id = cy * cols + cx
    strong = score >= ini_threshold
    has_strong = np.zeros(cols * rows, bool)
    has_strong[cell_id[strong]] = True
    keep = strong | ~has_strong[cell_id]
    return xy[keep], score[keep]


def quadtree_select(xy: np.ndarray, score: np.ndarray, bounds: tuple[float, float, float, float],
                    target: int, max_depth: int = 20) -> np.ndarray:
    """Indices of about ``target`` corners spread over ``bounds`` (x0, y0, x1, y1), keeping the best-scoring corner
    of each quadtree node. The root nodes are ~square columns; nodes holding more than one corner are split in four
    (empty children dropped) while the node count stays within ``target``; the round that would overshoot splits
    only the most crowded nodes, until ``target`` is reached.

    Vectorised by depth: the nodes after k full rounds are exactly the distinct depth-k cells holding a corner (a
    node with one corner stays one node however deep), so a cell code per corner replaces the node lists."""
    if target <= 0 or len(xy) == 0:
        return np.zeros(0, int)
    x0, y0, x1, y1 = bounds
    n_roots = max(1, int(round((x1 - x0) / max(y1 - y0, 1e-6))))
    u = np.clip((xy[:, 0] - x0) / (x1 - x0) * n_roots, 0, n_roots - 1e-9)
    v = np.clip((xy[:, 1] - y0) / (y1 - y0), 0, 1 - 1e-9)
    code = np.floor(u).astype(np.int64)  # depth 0: the root column
    u -= code

    def deeper(code: np.ndarray, depth: int) -> np.ndarray:  # child = 4 x parent + quadrant
        return 4 * code + 2 * (np.floor(v * 2**depth).astype(np.int64) & 1) + (np.floor(u * 2**depth).astype(
            np.int64) & 1)

    nodes = len(np.unique(code))
    for depth in range(1, max_depth + 1):
        if nodes >= target or nodes == len(xy):
            break
        child = deeper(code, depth)
        n_child = len(np.unique(child))
        if n_child <= target:  # a full round fits
            code, nodes = child, n_child
            continue
        parents, inverse, counts = np.unique(code, return_inverse=True, return_counts=True)
        kids = np.bincount(np.searchsorted(parents, np.unique(child) // 4), minlength=len(parents))
        order = np.argsort(-counts, kind="stable")  # the most crowded nodes first
        reached = nodes + np.cumsum(kids[order] - 1) >= target
        split = np.zeros(len(parents), bool)
        split[order[: int(np.argmax(reached)) + 1]] = True
        code = np.where(split[inverse], child, 4 * code)
        break
    best = np.lexsort((-score, code))  # per node code, best score first
    first = np.ones(len(best), bool)
    first[1:] = code[best][1:] != code[best][:-1]
    kept = best[first]
    return kept[np.argsort(-score[kept], kind="stable")[:target]]  # the last split may overshoot by up to 3


def intensity_centroid_angles(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Orientation (degrees, OpenCV's convention) of the intensity centroid in a disc of radius 15 at each corner."""
    if len(xy) == 0:
        return np.zeros(0, np.float32)
    r = HALF_PATCH
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float32)
    disc = dx**2 + dy**2 <= r * r + r  # the rasterised circle ORB's umax table describes
    moments = np.stack([(dx * disc).ravel(), (dy * disc).ravel()], axis=1)  # [31*31, 2]
    padded = cv2.copyMakeBorder(image, r, r, r, r, cv2.BORDER_REFLECT_101)
    windows = np.lib.stride_tricks.sliding_window_view(padded, (2 * r + 1, 2 * r + 1))
    x, y = np.rint(xy[:, 0]).astype(int), np.rint(xy[:, 1]).astype(int)
    patches = windows[y, x].reshape(len(xy), -1).astype(np.float32)  # patch centred on each corner
    m10, m01 = (patches @ moments).T
    return (np.rad2deg(np.arctan2(m01, m10)) % 360).astype(np.float32)


def orbslam_keypoints(gray: np.ndarray, total: int, levels: int = 8, scale_factor: float = 1.2,
                      ini_threshold: int = 20, min_threshold: int = 7) -> list[cv2.KeyPoint]:
    """ORB-SLAM's keypoints of a uint8 grey image as ``cv2.KeyPoint`` (level-0 pixels, octave = level, size and
    angle set), ready for ``cv2.ORB.compute``."""
    images = pyramid(gray, levels, scale_factor)
    shares = level_shares(total, len(images), scale_factor)
    out = []
    for level, (image, share) in enumerate(zip(images, shares, strict=True)):
        xy, score = grid_fast(image, ini_threshold, min_threshold)
        h, w = image.shape[:2]
        keep = quadtree_select(xy, score, (EDGE, EDGE, w - EDGE, h - EDGE), share)
        xy, score = xy[keep], score[keep]
        angles = intensity_centroid_angles(image, xy)
        scale = scale_factor**level
        out += [cv2.KeyPoint(float(x * scale), float(y * scale), PATCH_SIZE * scale, float(a), float(s), level)
                for (x, y), a, s in zip(xy, angles, score, strict=True)]
    return out
