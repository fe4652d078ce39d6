import cv2
import numpy as np
import pytest

from ruslam.data.procedural import ProceduralRGBD
from ruslam.eval.matching import evaluate_pair
from ruslam.models.extractor import Extractor
from ruslam.models.registry import load_extractor
from ruslam.models.rotation_tta import C4Augmented, best_rotation, extract_rotations, pool, rotated_to_original


class BrightestPixel(Extractor):
    """Detects the brightest pixel: its position in any rotated copy is known exactly."""

    def extract(self, image):
        y, x = np.unravel_index(np.argmax(image), image.shape[:2])
        return {"keypoints": np.array([[x, y]], np.float32), "scores": np.ones(1, np.float32),
                "descriptors": np.ones((1, 4), np.float32)}


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_keypoints_of_a_rotated_copy_map_back_exactly(k):
    img = np.zeros((30, 50), np.uint8)
    img[7, 41] = 255  # (x, y) = (41, 7) on a non-square image
    (x, y), = BrightestPixel().extract(np.rot90(img, k))["keypoints"]
    assert (x, y) != (41, 7) or k == 0
    assert np.array_equal(rotated_to_original([[x, y]], k, img.shape), [[41, 7]])
    parts = extract_rotations(BrightestPixel(), img)
    assert all(np.array_equal(p["keypoints"], [[41, 7]]) for p in parts)
    assert len(pool(parts)["keypoints"]) == 4


@pytest.fixture(scope="module")
def scene():
    return (ProceduralRGBD(num_images=1, height=128, width=160, seed=1)[0]["image"] * 255).astype(np.uint8)


def test_sift_keypoints_of_the_90_degree_copy_land_on_the_originals(scene):
    parts = extract_rotations(load_extractor("sift", max_keypoints=300), scene)
    upright = parts[0]["keypoints"]
    for part in parts[1:]:
        dist = np.linalg.norm(part["keypoints"][:, None] - upright[None], axis=-1).min(1)
        # SIFT is nearly equivariant to exact right-angle rotations; OpenCV's SIFT places keypoints ~0.25 px
        # down-right of the pixel-centre convention (its first octave doubles the image), which a rotation turns
        # into a 0.35-0.5 px gap; an off-by-one mapping would add a full pixel
        assert np.mean(dist < 0.75) > 0.7, np.mean(dist < 0.75)


def test_c4_reference_matches_a_rotated_query_the_plain_reference_does_not(scene):
    xfeat = load_extractor("xfeat", max_keypoints=400, vlad_codebook=None)
    h, w = scene.shape[:2]
    query = np.ascontiguousarray(np.rot90(scene, -1))  # rotated 90° clockwise: an upright learned feature fails
    # H from image 1 to the query: the pixel (x, y) of the scene goes to (h - 1 - y, x)
    H = np.array([[0, -1, h - 1], [1, 0, 0], [0, 0, 1]], np.float64)
    assert np.array_equal(query[5, h - 1 - 20], scene[20, 5])
    features2 = xfeat.extract(query)
    plain = evaluate_pair(xfeat.extract(scene), features2, H, (h, w), (w, h), binary=False, max_keypoints=400)
    c4 = C4Augmented(xfeat)
    tta = evaluate_pair(c4.extract(scene), features2, H, (h, w), (w, h), binary=False, max_keypoints=0)
    assert plain.mma[2] < 0.2 and tta.mma[2] > 0.6, (plain.mma[2], tta.mma[2])
    assert not c4.binary and C4Augmented(load_extractor("orb")).binary


def test_c4_keeps_binary_descriptors(scene):
    out = C4Augmented(load_extractor("orb", max_keypoints=200)).extract(cv2.cvtColor(scene, cv2.COLOR_RGB2GRAY))
    assert out["descriptors"].dtype == np.uint8 and len(out["keypoints"]) == len(out["descriptors"]) > 200


@pytest.mark.parametrize("k", [1, 2, 3])
def test_the_best_rotation_is_the_copy_the_query_was_turned_by(scene, k):
    xfeat = load_extractor("xfeat", max_keypoints=400, vlad_codebook=None)
    parts = extract_rotations(xfeat, scene)
    query = xfeat.extract(np.ascontiguousarray(np.rot90(scene, k)))
    assert best_rotation(parts, query) == k
    # binary descriptors: an upright query agrees best with the upright copy (its own keypoints, Hamming 0)
    orb = load_extractor("orb", max_keypoints=300)
    grey = cv2.cvtColor(scene, cv2.COLOR_RGB2GRAY)
    assert best_rotation(extract_rotations(orb, grey), orb.extract(grey), binary=True) == 0
