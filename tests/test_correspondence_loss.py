"""Correspondence loss: ~0 when the two views' descriptors correspond exactly, large when they are shuffled."""

import math

import torch
import torch.nn.functional as F

from ruslam.models.correspondence_loss import CorrespondenceLoss, cell_centres, transfer


def _dense(b=2, d=64, h=12, w=16, seed=0):
    return F.normalize(torch.randn(b, d, h, w, generator=torch.Generator().manual_seed(seed)), dim=1)


def test_identical_views_give_near_zero_and_shuffled_views_a_large_loss():
    loss = CorrespondenceLoss(temperature=0.05, num_samples=128)
    desc = _dense()
    eye = torch.eye(3).expand(2, 3, 3)
    same = loss(desc, desc.clone(), eye)
    perm = torch.randperm(12 * 16, generator=torch.Generator().manual_seed(1))
    shuffled = desc.flatten(2)[:, :, perm].reshape(desc.shape)
    wrong = loss(desc, shuffled, eye)
    assert same < 1e-3
    assert wrong > 0.5 * math.log(128)  # no better than chance


def test_the_homography_is_followed():
    """View B is view A shifted by one cell; the loss is ~0 only when the homography says so."""
    loss = CorrespondenceLoss(temperature=0.05, num_samples=64)
    desc_a = _dense(b=1)
    desc_b = torch.roll(desc_a, shifts=1, dims=3)  # B(u+1) = A(u): a shift of +8 px in x
    shift = torch.tensor([[[1.0, 0, 8], [0, 1, 0], [0, 0, 1]]])
    assert loss(desc_a, desc_b, shift) < 1e-3
    assert loss(desc_a, desc_b, torch.eye(3)[None]) > 1.0


def test_invalid_cells_and_points_leaving_view_b_are_not_sampled():
    loss = CorrespondenceLoss(temperature=0.05, num_samples=64)
    desc = _dense(b=1)
    mask = torch.zeros(1, 12, 16)
    far = torch.tensor([[[1.0, 0, 1000], [0, 1, 0], [0, 0, 1]]])  # everything lands outside B
    assert loss(desc, desc, torch.eye(3)[None], mask) == 0
    assert loss(desc, desc, far) == 0


def test_transfer_and_cell_centres_follow_the_pixel_convention():
    c = cell_centres(2, 3)
    assert torch.equal(c[:4], torch.tensor([[3.5, 3.5], [11.5, 3.5], [19.5, 3.5], [3.5, 11.5]]))
    h = torch.tensor([[2.0, 0, 1], [0, 2, -1], [0, 0, 1]])
    assert torch.allclose(transfer(c[:1], h), torch.tensor([[8.0, 6.0]]))


def test_reliability_loss_rewards_a_map_that_knows_which_cells_match():
    """Half of B's cells are shuffled: a reliability map that is high on the intact half and low on the shuffled
    half scores a much lower loss than the inverted map (and than a constant 0.5)."""
    from ruslam.models.reliability_loss import ReliabilityLoss

    loss, rel = CorrespondenceLoss(num_samples=1000), ReliabilityLoss()
    desc_a = _dense(b=1)
    flat = desc_a.flatten(2).clone()
    broken = torch.arange(12 * 16) % 2 == 1  # every other cell of B is replaced by another image's descriptor
    flat[:, :, broken] = _dense(b=1, seed=5).flatten(2)[:, :, broken]
    desc_b = flat.reshape(desc_a.shape)
    samples = loss.sample(desc_a, desc_b, torch.eye(3)[None])
    good = (~broken).float().reshape(1, 1, 12, 16) * 0.98 + 0.01
    assert rel(good, samples) < 0.05
    assert rel(1 - good, samples) > 3.0
    assert rel(torch.full_like(good, 0.5), samples) > 0.6
    assert rel(good, []) == 0
