"""Exact cases of the matching metrics; every expected value is computed by hand in the comments."""

import numpy as np
import pytest

from ruslam import load_extractor
from ruslam.eval.matching import (
    evaluate_pair,
    mutual_nearest_neighbours,
    rotation_bin,
    summarize,
    warp_points,
)

SHAPE = (100, 100)


def onehot(i, extra=None, dim=10):
    v = np.zeros(dim, np.float32)
    v[i] = 1.0
    if extra is not None:
        v[extra] = 0.1
    return v


def feats(kps, descs, scores=None):
    kps = np.array(kps, np.float32)
    scores = np.ones(len(kps), np.float32) if scores is None else np.array(scores, np.float32)
    return {"keypoints": kps, "scores": scores, "descriptors": np.array(descs)}


def textured_image(seed=0, h=240, w=320):
    rng = np.random.default_rng(seed)
    small = (rng.random((h // 8, w // 8)) * 255).astype(np.uint8)
    img = np.kron(small, np.ones((8, 8), np.uint8))
    return np.dstack([img] * 3)


@pytest.mark.parametrize("name", ["sift", "orb"])
def test_identity_homography_gives_full_repeatability_and_mma(name):
    extractor = load_extractor(name)
    img = textured_image()
    f1, f2 = extractor.extract(img), extractor.extract(img)  # deterministic detector: identical outputs
    assert len(f1["keypoints"]) > 50
    res = evaluate_pair(f1, f2, np.eye(3), img.shape[:2], img.shape[:2], binary=extractor.binary)
    assert res.repeatability == 1.0
    assert np.all(res.mma == 1.0)
    assert res.num_matches > 50 and np.all(res.match_errors == 0)


def test_translation_by_hand():
    # x2 = x1 + 30. Image-1 keypoint d warps to x = 110 (outside image 2); image-2 keypoint D warps back to
    # x = -20 (outside image 1). Both carry a descriptor that would steal a match if they were counted.
    H = np.array([[1, 0, 30], [0, 1, 0], [0, 0, 1]], float)
    f1 = feats(
        [(10, 10), (20, 50), (50, 50), (80, 20), (60, 70)],  # a b c d e
        [onehot(0, 5), onehot(1), onehot(2), onehot(0), onehot(3)],
    )
    f2 = feats(
        [(40, 10), (52, 50), (85, 50), (10, 90), (90, 77)],  # A (0 px) B (2 px) C (5 px) D E (7 px)
        [onehot(0), onehot(1), onehot(2), onehot(3), onehot(3, 6)],
    )
    res = evaluate_pair(f1, f2, H, SHAPE, SHAPE, binary=False)
    assert res.num_keypoints == (4, 4)  # d and D are outside the shared view
    # repeated within 3 px: a, b from image 1 and A, B from image 2 -> 4 / (4 + 4)
    assert res.repeatability == pytest.approx(0.5)
    # mutual NN: a-A (0 px), b-B (2 px), c-C (5 px), e-E (7 px)
    assert res.num_matches == 4
    assert sorted(res.match_errors.tolist()) == pytest.approx([0, 2, 5, 7])
    expected_mma = [1 / 4, 2 / 4, 2 / 4, 2 / 4, 3 / 4, 3 / 4, 1, 1, 1, 1]  # thresholds 1..10
    assert res.mma.tolist() == pytest.approx(expected_mma)
    assert res.matching_score == pytest.approx(2 / 4)  # 2 correct at 3 px over mean(4, 4)


def test_scaling_by_hand():
    H = np.diag([2.0, 2.0, 1.0])  # x2 = 2 x1; the shared view of image 1 is x, y < 49.75
    f1 = feats([(10, 10), (30, 40), (45, 45), (60, 10)], [onehot(0), onehot(1), onehot(2), onehot(3)])
    f2 = feats([(21, 20), (60, 84), (90, 90), (5, 5)], [onehot(0), onehot(1), onehot(2), onehot(9)])
    res = evaluate_pair(f1, f2, H, SHAPE, SHAPE, binary=False)
    assert res.num_keypoints == (3, 4)
    # image 1 -> 2: (20,20) vs (21,20) 1 px yes; (60,80) vs (60,84) 4 px no; (90,90) 0 px yes: 2
    # image 2 side: (21,20) yes, (60,84) no, (90,90) yes, (5,5) no: 2 -> 4 / 7
    assert res.repeatability == pytest.approx(4 / 7)
    assert res.num_matches == 3  # (5,5) has an unrelated descriptor: not mutual
    assert res.mma.tolist() == pytest.approx([2 / 3, 2 / 3, 2 / 3] + [1] * 7)
    assert res.matching_score == pytest.approx(2 / 3.5)


def test_keypoint_outside_shared_view_never_counts():
    H = np.array([[1, 0, 30], [0, 1, 0], [0, 0, 1]], float)
    base1 = feats([(10, 10), (20, 20)], [onehot(0), onehot(1)])
    base2 = feats([(40, 10), (50, 20)], [onehot(0), onehot(1)])
    ref = evaluate_pair(base1, base2, H, SHAPE, SHAPE, binary=False)
    # add, in image 1, a keypoint at x = 75 (warps to 105, outside) that is a perfect copy of the first one
    # and sits exactly on an image-2 keypoint's warp; it must change nothing.
    extra1 = feats([(10, 10), (20, 20), (75, 10)], [onehot(0), onehot(1), onehot(0)])
    extra2 = feats([(40, 10), (50, 20), (-0.6, 50)], [onehot(0), onehot(1), onehot(1)])  # x = -0.6: outside
    res = evaluate_pair(extra1, extra2, H, SHAPE, SHAPE, binary=False)
    assert res.num_keypoints == ref.num_keypoints == (2, 2)
    assert (res.repeatability, res.matching_score, res.num_matches) == (1.0, 1.0, 2)
    assert np.array_equal(res.mma, ref.mma)


def test_cap_applies_to_whole_image_before_shared_view():
    H = np.array([[1, 0, 30], [0, 1, 0], [0, 0, 1]], float)
    # the best-scoring image-1 keypoint is outside the shared view: with a cap of 1 nothing is left in image 1
    f1 = feats([(90, 10), (10, 10)], [onehot(0), onehot(1)], scores=[0.9, 0.1])
    f2 = feats([(40, 10)], [onehot(1)])
    capped = evaluate_pair(f1, f2, H, SHAPE, SHAPE, binary=False, max_keypoints=1)
    assert capped.num_keypoints == (0, 1) and capped.num_matches == 0 and capped.repeatability == 0.0
    uncapped = evaluate_pair(f1, f2, H, SHAPE, SHAPE, binary=False, max_keypoints=2)
    assert uncapped.num_keypoints == (1, 1) and uncapped.repeatability == 1.0


def test_hamming_mutual_nearest_neighbours():
    d1 = np.array([[0b11110000], [0b00001111], [0b10101010]], np.uint8)
    d2 = np.array([[0b00001110], [0b11110001]], np.uint8)
    # distances: row0 -> (8, 1), row1 -> (1, 7), row2 -> (5, 4); col0 best row1, col1 best row0
    assert mutual_nearest_neighbours(d1, d2, binary=True).tolist() == [[0, 1], [1, 0]]


def test_empty_detection_scores_zero():
    empty = {"keypoints": np.zeros((0, 2)), "scores": np.zeros(0), "descriptors": np.zeros((0, 8), np.float32)}
    other = feats([(10, 10)], [onehot(0, dim=8)])
    res = evaluate_pair(empty, other, np.eye(3), SHAPE, SHAPE, binary=False)
    assert (res.repeatability, res.matching_score, res.num_matches) == (0.0, 0.0, 0)
    assert np.all(res.mma == 0)


def test_warp_and_bins_and_summary():
    H = np.array([[0, -1, 99], [1, 0, 0], [0, 0, 1]], float)  # 90 degree rotation
    assert warp_points(np.array([[10, 20]]), H).tolist() == [[79, 10]]
    assert [rotation_bin(a) for a in (0, 29.9, 30, -45, 89.99, 90, 180, -180, 181)] == [0, 0, 1, 1, 1, 2, 2, 2, -1]
    H = np.array([[1, 0, 30], [0, 1, 0], [0, 0, 1]], float)
    a = evaluate_pair(feats([(10, 10)], [onehot(0)]), feats([(40, 10)], [onehot(0)]), H, SHAPE, SHAPE, False)
    b = evaluate_pair(feats([(10, 10)], [onehot(0)]), feats([(45, 10)], [onehot(0)]), H, SHAPE, SHAPE, False)
    s = summarize([a, b])
    # a: rep 1, ms 1, all mma 1; b: 5 px off -> rep 0, ms 0, mma 0 below 5 px, 1 from 5 px
    assert (s["pairs"], s["rep"], s["ms"], s["mma"]) == (2, 50.0, 50.0, 50.0)
    assert s["mma_curve"] == pytest.approx([50, 50, 50, 50, 100, 100, 100, 100, 100, 100])
