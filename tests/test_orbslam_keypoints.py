"""ORB as ORB-SLAM extracts it: budget per level, adaptive FAST threshold, quadtree spreading, oriented rBRIEF."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ruslam.models.classical import ORB
from ruslam.models.orbslam_keypoints import grid_fast, level_shares, quadtree_select


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """Blob texture (blurred noise) over smooth shading, 360x480 grey."""
    rng = np.random.default_rng(0)
    blobs = cv2.GaussianBlur(rng.standard_normal((360, 480)), (0, 0), 1.5)
    shade = cv2.resize(rng.standard_normal((4, 5)), (480, 360), interpolation=cv2.INTER_CUBIC)
    return np.clip(128 + 130 * blobs + 15 * shade, 0, 255).astype(np.uint8)


def _low_contrast(image: np.ndarray, c: float) -> np.ndarray:
    return np.clip(128 + c * (image.astype(np.float64) - 128), 0, 255).astype(np.uint8)


def test_level_shares_follow_the_scale_and_sum_to_the_budget():
    shares = level_shares(1000, 8, 1.2)
    assert sum(shares) == 1000 and len(shares) == 8
    assert shares[0] == pytest.approx(1000 * (1 - 1 / 1.2) / (1 - 1.2**-8), abs=1)
    assert all(a > b for a, b in zip(shares[:6], shares[1:7], strict=True))


def test_quadtree_spreads_instead_of_taking_the_strongest():
    """A crowded strong cluster and a few weak isolated corners: the tree keeps every isolated one."""
    rng = np.random.default_rng(1)
    cluster = rng.uniform(0, 20, (500, 2))
    isolated = np.array([[150, 30], [250, 90], [60, 180], [280, 200], [180, 150], [30, 100]], float)
    xy = np.vstack([cluster, isolated])
    score = np.concatenate([rng.uniform(50, 100, 500), np.full(6, 8.0)])
    keep = quadtree_select(xy, score, (0, 0, 300, 220), 30)
    assert len(keep) == 30 and len(set(keep)) == 30
    assert set(range(500, 506)) <= set(keep)  # all the weak isolated corners survive
    assert np.argsort(-score)[:30].tolist() != sorted(keep)  # which plain top-30 by score would not give
    pair = quadtree_select(np.array([[10.0, 10.0], [10.2, 10.1]]), np.array([3.0, 5.0]), (0, 0, 100, 100), 1)
    assert pair.tolist() == [1]  # one node: its best corner


def test_adaptive_threshold_only_where_a_cell_has_nothing_strong(texture):
    image = texture.copy()
    image[:, 240:] = _low_contrast(texture[:, 240:], 0.15)  # right half faint
    xy, score = grid_fast(image, 20, 7)
    left, right = xy[:, 0] < 230, xy[:, 0] > 250
    assert score[left].min() >= 20  # strong cells keep only strong corners
    assert right.sum() > 50 and score[right].min() < 20  # faint cells fall back to the low threshold


def test_orbslam_orb_keeps_working_where_plain_orb_finds_nothing(texture):
    faint = _low_contrast(texture, 0.15)
    plain = ORB(max_keypoints=1000, distribution="opencv").extract(faint)
    ours = ORB(max_keypoints=1000).extract(faint)
    assert len(plain["keypoints"]) < 50 <= 300 < len(ours["keypoints"]) <= 1000
    assert ours["descriptors"].shape == (len(ours["keypoints"]), 32) and ours["descriptors"].dtype == np.uint8
    full = ORB(max_keypoints=1000).extract(texture)
    assert len(full["keypoints"]) <= 1000
    cells = np.unique((full["keypoints"] // 40).astype(int), axis=0)
    assert len(cells) > 0.8 * (480 // 40) * (360 // 40)  # spread over the image


@pytest.mark.parametrize("contrast", [1.0, 0.15])
def test_descriptors_are_rotation_invariant(texture, contrast):
    """Intensity-centroid angles in OpenCV's convention: a 90-degree rotation leaves the matches correct."""
    image = _low_contrast(texture, contrast)
    orb = ORB(max_keypoints=1000)
    a, b = orb.extract(image), orb.extract(np.ascontiguousarray(np.rot90(image)))
    w = image.shape[1]
    expected = np.column_stack([a["keypoints"][:, 1], w - 1 - a["keypoints"][:, 0]])  # rot90: (x, y) -> (y, W-1-x)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a["descriptors"], b["descriptors"])
    correct = [np.linalg.norm(expected[m.queryIdx] - b["keypoints"][m.trainIdx]) < 3 for m in matches]
    assert len(matches) > 0.5 * len(a["keypoints"]) and np.mean(correct) > 0.9


def test_orb_options_are_checked():
    with pytest.raises(ValueError, match="distribution"):
        ORB(distribution="grid")
