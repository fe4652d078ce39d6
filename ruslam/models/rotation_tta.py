"""C4 test-time augmentation: extract on an image rotated by 0/90/180/270° and pool the features in its pixels.

For an extractor that is not rotation invariant, a reference image (a keyframe, image 1 of a homography pair)
extracted at the four right-angle rotations holds, for any in-plane rotation of a query, a copy within 45° of
it. Keypoints found in ``np.rot90(image, k)`` are mapped back to the input's pixels exactly (pixel centres at
integers); descriptors and scores are kept as they are. The query image is extracted once, as usual, so the
per-frame cost is unchanged and the reference costs 4 extractions.

Two ways to match a query against the four copies: pool them (`pool`, `C4Augmented`: mutual nearest neighbours
over up to 4x the keypoints, so the three wrong copies add distractors), or first pick the copy the query agrees
with (`best_rotation`: the most ratio-test mutual matches, no geometry) and match against it alone.

Works with any extractor of the contract (float or binary descriptors); ``global_descriptor`` comes from the
upright image.
"""

from __future__ import annotations

import numpy as np

from ruslam.models.extractor import Extractor, check_image
from ruslam.models.feature_matching import match_knn_ratio

ROTATIONS = (0, 1, 2, 3)  # multiples of 90° counter-clockwise, as np.rot90


def rotated_to_original(points: np.ndarray, k: int, hw: tuple[int, int]) -> np.ndarray:
    """Map (x, y) pixels of ``np.rot90(image, k)`` back to pixels of ``image`` (of shape ``hw``)."""
    h, w = hw
    x, y = np.asarray(points, dtype=np.float64).reshape(-1, 2).T
    k %= 4
    if k == 0:
        out = (x, y)
    elif k == 1:  # rot90[i, j] = image[j, W-1-i]
        out = (w - 1 - y, x)
    elif k == 2:
        out = (w - 1 - x, h - 1 - y)
    else:  # rot90(k=3)[i, j] = image[H-1-j, i]
        out = (y, h - 1 - x)
    return np.stack(out, axis=1).astype(np.float32)


def extract_rotations(extractor: Extractor, image: np.ndarray, rotations=ROTATIONS) -> list[dict]:
    """One feature dict per rotation, keypoints in the input image's pixels (the first is the plain extraction)."""
    image = check_image(image)
    parts = []
    for k in rotations:
        out = dict(extractor.extract(np.ascontiguousarray(np.rot90(image, k))))
        out["keypoints"] = rotated_to_original(out["keypoints"], k, image.shape[:2])
        parts.append(out)
    return parts


def pool(parts: list[dict]) -> dict:
    """The union of several feature dicts of one image (global descriptor of the first)."""
    out = {key: np.concatenate([p[key] for p in parts], axis=0) for key in ("keypoints", "scores", "descriptors")}
    if "global_descriptor" in parts[0]:
        out["global_descriptor"] = parts[0]["global_descriptor"]
    return out


def best_rotation(parts: list[dict], query: dict, binary: bool = False, ratio: float = 0.9) -> int:
    """Index of the part (one reference rotation) with the most mutual nearest-neighbour matches to ``query``
    that pass a 2-NN ratio test: the copy nearest to the query's rotation, chosen from descriptors alone."""
    counts = [len(match_knn_ratio(np.asarray(p["descriptors"]), np.asarray(query["descriptors"]), binary,
                                  max_distance=np.inf, ratio=ratio)[0]) for p in parts]
    return int(np.argmax(counts))


class C4Augmented(Extractor):
    """Any extractor with C4 test-time augmentation: up to 4x its keypoints, each with its own descriptor."""

    def __init__(self, extractor: Extractor):
        super().__init__()
        self.extractor = extractor
        self.binary = getattr(extractor, "binary", False)

    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        return pool(extract_rotations(self.extractor, image))
