"""Geometric augmentation warps the teacher targets exactly like the student's image."""

import math

import numpy as np
import torch
import torch.nn.functional as F

from ruslam.models.extractor import cell_logits_to_heatmap
from ruslam.training.augment import GeometricAugment, PhotometricAugment, seeded_generator, warp_image, warp_targets


def _rotation(angle_deg, size):
    a = math.radians(angle_deg)
    c = (size - 1) / 2
    t = torch.tensor([[1, 0, -c], [0, 1, -c], [0, 0, 1]], dtype=torch.float64)
    r = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], dtype=torch.float64)
    return torch.linalg.inv(t) @ r @ t


def _targets(seed=0, h=8, w=8, d=4):
    g = torch.Generator().manual_seed(seed)
    logits = torch.full((65, h, w), -5.0)
    logits[64] = 5.0  # dustbin everywhere...
    logits[8 * 2 + 5, 1, 6] = 12.0  # ...but one sharp keypoint: cell (row 1, col 6), in-cell (row 2, col 5)
    return {"keypoint_logits": logits, "dense_descriptors": F.normalize(torch.randn(d, h, w, generator=g), dim=0),
            "global_descriptor": torch.randn(16, generator=g)}


def test_quarter_turn_moves_keypoints_and_descriptors_with_the_image():
    t = _targets()
    hom = _rotation(90, 64)
    out = warp_targets(t, hom)
    # Keypoint at pixel (x=6*8+5, y=1*8+2) = (53, 10); the homography sends it to (63 - 10, 53) = (53, 53).
    heat = cell_logits_to_heatmap(out["keypoint_logits"][None])[0]
    y, x = divmod(int(heat.argmax()), 64)
    assert (x, y) == (53, 53)
    src = torch.linalg.solve(hom, torch.tensor([53.0, 53.0, 1.0], dtype=torch.float64))
    assert torch.allclose(src[:2] / src[2], torch.tensor([53.0, 10.0], dtype=torch.float64))
    # Cell centres map onto cell centres: the descriptor map is the source map turned by a quarter, values kept.
    expected = torch.rot90(t["dense_descriptors"], k=-1, dims=(1, 2))
    torch.testing.assert_close(out["dense_descriptors"], expected, atol=1e-5, rtol=1e-5)
    assert out["mask"].all()
    torch.testing.assert_close(out["global_descriptor"], t["global_descriptor"])
    # The image itself moves the same way.
    img = torch.zeros(1, 64, 64)
    img[0, 10, 53] = 1.0
    assert int(warp_image(img, hom)[0].argmax()) == 53 * 64 + 53


def test_rotation_masks_cells_brought_in_from_outside_and_keeps_distributions():
    out = warp_targets(_targets(), _rotation(45, 64))
    assert not out["mask"][0, 0] and not out["mask"][-1, -1]  # corners come from outside
    assert out["mask"][3:5, 3:5].all()
    torch.testing.assert_close(out["keypoint_logits"].exp().sum(0), torch.ones(8, 8), atol=1e-4, rtol=1e-4)
    valid = out["mask"] > 0
    torch.testing.assert_close(out["dense_descriptors"].norm(dim=0)[valid], torch.ones(int(valid.sum())))


def test_identity_warp_changes_nothing():
    t = _targets()
    out = warp_targets(t, torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(out["keypoint_logits"].softmax(0), t["keypoint_logits"].softmax(0), atol=1e-4, rtol=0)
    torch.testing.assert_close(out["dense_descriptors"], t["dense_descriptors"], atol=1e-5, rtol=0)
    assert out["mask"].all()


def test_sampling_is_seeded_and_covers_large_rotations():
    aug = GeometricAugment(max_rotation_deg=180, rotation_prob=1.0, perspective=0.0, scale=(1.0, 1.0))
    a = aug.sample(48, 64, seeded_generator(0, 0, 3))
    b = aug.sample(48, 64, seeded_generator(0, 0, 3))
    torch.testing.assert_close(a, b)
    angles = [abs(math.degrees(math.atan2(h[1, 0], h[0, 0]))) for h in
              (aug.sample(48, 64, seeded_generator(0, 0, i)) for i in range(200))]
    assert max(angles) > 150 and min(angles) < 20
    small = GeometricAugment(rotation_prob=0.0, small_rotation_deg=10, scale=(1.0, 1.0), perspective=0.0)
    assert all(abs(math.degrees(math.atan2(h[1, 0], h[0, 0]))) <= 10 + 1e-6 for h in
               (small.sample(48, 64, seeded_generator(1, 0, i)) for i in range(50)))


def test_photometric_is_seeded_and_stays_in_range():
    img = torch.rand(3, 16, 16)
    aug = PhotometricAugment()
    a, b = aug(img, seeded_generator(5)), aug(img, seeded_generator(5))
    torch.testing.assert_close(a, b)
    assert not torch.equal(a, aug(img, seeded_generator(6)))
    assert a.min() >= 0 and a.max() <= 1


class _Cache:
    def __init__(self, h, w):
        g = torch.Generator().manual_seed(0)
        self.targets = {"keypoint_logits": torch.randn(65, h // 8, w // 8, generator=g).numpy(),
                        "dense_descriptors": torch.randn(64, h // 8, w // 8, generator=g).numpy(),
                        "global_descriptor": torch.randn(4096, generator=g).numpy()}

    def read(self, key):
        return dict(self.targets)


def test_pair_views_carry_the_homography_between_them():
    """Pixel p of view A shows the same image point as pixel H_ab p of view B."""
    from ruslam.training.datamodule import DistillationDataset  # noqa: PLC0415

    h, w = 96, 128
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    image = np.stack([np.sin(xx / 7) * 0.5 + 0.5, np.cos(yy / 9) * 0.5 + 0.5, (xx + yy) / (h + w)], -1)
    source = [{"id": 0, "image": image, "depth": np.ones((h, w), np.float32)}]
    data = DistillationDataset(source, [0], _Cache(h, w), geometric=GeometricAugment(), pair_views=True)
    sample = data[0]
    a, b, hom = sample["image"], sample["pair"]["image"], sample["homography_ab"].double()
    assert not torch.equal(a, b) and sample["pair"]["mask"].shape == sample["mask"].shape
    pts = torch.stack(torch.meshgrid(torch.arange(20, w - 20, 6), torch.arange(20, h - 20, 6), indexing="xy"),
                      -1).reshape(-1, 2).double()
    q = torch.cat([pts, torch.ones(len(pts), 1, dtype=torch.float64)], 1) @ hom.T
    q = q[:, :2] / q[:, 2:]
    inside = (q[:, 0] > 2) & (q[:, 0] < w - 3) & (q[:, 1] > 2) & (q[:, 1] < h - 3)
    va = a[:, pts[inside, 1].long(), pts[inside, 0].long()]
    qi = q[inside].round().long()
    vb = b[:, qi[:, 1], qi[:, 0]]
    assert inside.sum() > 20
    assert (va - vb).abs().mean() < 0.05  # rounding to the nearest pixel leaves a small error
    wrong = b[:, pts[inside, 1].long(), pts[inside, 0].long()]  # ignoring the homography
    assert (va - wrong).abs().mean() > 2 * (va - vb).abs().mean()
