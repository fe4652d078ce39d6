import torch

from ruslam.models.repeatability_loss import RepeatabilityLoss


def _shift(dx: float) -> torch.Tensor:
    return torch.tensor([[1.0, 0, dx], [0, 1, 0], [0, 0, 1]])[None]


def test_agreeing_views_score_zero_and_moved_peaks_do_not():
    torch.manual_seed(0)
    logits = torch.randn(1, 65, 6, 8) * 3
    loss = RepeatabilityLoss(patch=8)
    assert loss(logits, logits, torch.eye(3)[None]) < 1e-4
    # view B = view A shifted 8 px (one cell) right: B's logits are A's rolled by one cell
    shifted = torch.roll(logits, 1, dims=3)
    assert loss(logits, shifted, _shift(8.0)) < 1e-4
    # the same B read as if it were not shifted: peaks disagree
    assert loss(logits, shifted, torch.eye(3)[None]) > 0.2
    assert loss(logits, torch.randn(1, 65, 6, 8) * 3, torch.eye(3)[None]) > 0.2


def test_gradient_reaches_both_views_and_nothing_valid_gives_zero():
    a = torch.randn(2, 65, 4, 4, requires_grad=True)
    b = torch.randn(2, 65, 4, 4, requires_grad=True)
    out = RepeatabilityLoss(patch=8)(a, b, torch.eye(3).repeat(2, 1, 1))
    out.backward()
    assert a.grad.abs().sum() > 0 and b.grad.abs().sum() > 0
    far = _shift(1000.0).repeat(2, 1, 1)  # A maps outside B everywhere
    assert RepeatabilityLoss(patch=8)(a, b, far) == 0


def test_a_flat_heat_does_not_count_as_agreement():
    flat = torch.zeros(1, 65, 4, 4)  # every pixel of every cell equally likely
    assert RepeatabilityLoss(patch=8)(flat, flat, torch.eye(3)[None]) > 0.99
