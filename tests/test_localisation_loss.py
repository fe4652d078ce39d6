import torch
import torch.nn.functional as F

from ruslam.models.localisation_loss import LocalisationLoss


def _blobs(centres, h=48, w=64, sigma=1.0) -> torch.Tensor:
    """Cell logits [1, 65, h/8, w/8] whose heat has a Gaussian peak at each (x, y) centre (sub-pixel allowed)."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                            indexing="ij")
    heat = sum(torch.exp(-((xs - x) ** 2 + (ys - y) ** 2) / (2 * sigma**2)) for x, y in centres)
    logits = F.pixel_unshuffle(torch.log(heat + 1e-6)[None, None], 8)
    # a dominant dustbin makes every cell's softmax nearly the same scale, so the heat is the blobs themselves
    return torch.cat([logits, torch.full_like(logits[:, :1], 4.0)], 1)


def _shift(dx: float, dy: float = 0.0) -> torch.Tensor:
    return torch.tensor([[1.0, 0, dx], [0, 1, dy], [0, 0, 1]])[None]


CENTRES = [(12.3, 11.6), (36.0, 12.5), (20.6, 30.2), (50.4, 33.0)]


def test_peaks_found_where_the_homography_says_score_zero_and_moved_ones_score_their_offset():
    loss = LocalisationLoss(radius=4, top_k=8)
    a = _blobs(CENTRES)
    assert loss(a, a, torch.eye(3)[None]) < 0.05
    # view B holds the same peaks 3.5 px right, 1 px down, and the homography says so
    moved = _blobs([(x + 3.5, y + 1.0) for x, y in CENTRES])
    assert loss(a, moved, _shift(3.5, 1.0)) < 0.05
    # the same B read as if it were not moved: each peak is found ~sqrt(3.5^2 + 1) = 3.6 px from where it should be
    assert 3.0 < loss(a, moved, torch.eye(3)[None]) < 4.0
    # a 1.5 px miss counts 1.5 px (not clipped, not zero)
    assert 1.3 < loss(a, _blobs([(x + 1.5, y) for x, y in CENTRES]), torch.eye(3)[None]) < 1.7


def test_gradient_reaches_both_views_and_no_keypoint_gives_zero():
    a = _blobs(CENTRES).requires_grad_(True)
    b = _blobs([(x + 1.5, y) for x, y in CENTRES]).requires_grad_(True)
    LocalisationLoss(top_k=8)(a, b, torch.eye(3)[None]).backward()
    assert a.grad.abs().sum() > 0 and b.grad.abs().sum() > 0
    assert LocalisationLoss()(a, b, _shift(1000.0)) == 0  # every keypoint lands outside the other view
    none_valid = torch.zeros(1, 6, 8)
    assert LocalisationLoss()(a, b, torch.eye(3)[None], none_valid, none_valid) == 0
