"""Eq. 8: the weighted sum, each term against a hand computation, gradients reaching alpha, beta, gamma."""

import math

import torch
import torch.nn.functional as F

from ruslam.models.distillation_loss import DistillationLoss


def _pair(seed=0, b=2, d=4, h=3, w=5):
    g = torch.Generator().manual_seed(seed)
    pred = {"keypoint_logits": torch.randn(b, 65, h, w, generator=g),
            "dense_descriptors": F.normalize(torch.randn(b, d, h, w, generator=g), dim=1),
            "global_descriptor": F.normalize(torch.randn(b, 8, generator=g), dim=1)}
    target = {"keypoint_logits": torch.randn(b, 65, h, w, generator=g),
              "dense_descriptors": F.normalize(torch.randn(b, d, h, w, generator=g), dim=1),
              "global_descriptor": F.normalize(torch.randn(b, 8, generator=g), dim=1)}
    return pred, target


def test_terms_match_a_hand_computation_on_one_cell():
    pred, target = _pair(b=1, h=1, w=1)
    t = DistillationLoss.terms(pred, target)
    p = target["keypoint_logits"][0, :, 0, 0].softmax(0)
    q = pred["keypoint_logits"][0, :, 0, 0].softmax(0)
    assert math.isclose(t["detector"].item(), -(p * q.log()).sum().item(), rel_tol=1e-5)
    d = pred["dense_descriptors"][0, :, 0, 0] - target["dense_descriptors"][0, :, 0, 0]
    assert math.isclose(t["local"].item(), (d * d).sum().item(), rel_tol=1e-5)
    gd = pred["global_descriptor"][0] - target["global_descriptor"][0]
    assert math.isclose(t["global"].item(), (gd * gd).sum().item(), rel_tol=1e-5)


def test_identical_prediction_gives_zero_descriptor_losses_and_entropy_detector_loss():
    pred, target = _pair()
    t = DistillationLoss.terms(target, target)
    assert t["global"].item() < 1e-10 and t["local"].item() < 1e-10
    p = target["keypoint_logits"].softmax(1)
    entropy = -(p * p.log()).sum(1).mean()
    assert math.isclose(t["detector"].item(), entropy.item(), rel_tol=1e-5)
    assert DistillationLoss.terms(pred, target)["detector"] > entropy


def test_mask_excludes_invalid_cells():
    pred, target = _pair()
    mask = torch.zeros(2, 3, 5)
    mask[:, 1, 2] = 1
    masked = DistillationLoss.terms(pred, target, mask)
    one = {k: v[:, :, 1:2, 2:3] if v.ndim == 4 else v for k, v in pred.items()}
    one_t = {k: v[:, :, 1:2, 2:3] if v.ndim == 4 else v for k, v in target.items()}
    ref = DistillationLoss.terms(one, one_t)
    for key in ("local", "detector"):
        assert math.isclose(masked[key].item(), ref[key].item(), rel_tol=1e-5)
    # Garbage in invalid cells changes nothing.
    pred["dense_descriptors"][:, :, 0] = 100.0
    assert math.isclose(DistillationLoss.terms(pred, target, mask)["local"].item(), ref["local"].item(), rel_tol=1e-5)


def test_weighted_total_is_equation_8_and_gradients_reach_alpha_beta_gamma():
    pred, target = _pair()
    loss = DistillationLoss()
    with torch.no_grad():
        loss.alpha.fill_(0.3)
        loss.beta.fill_(-0.2)
        loss.gamma.fill_(0.7)
    out = loss(pred, target)
    t = DistillationLoss.terms(pred, target)
    expected = (math.exp(-0.3) * t["global"] + math.exp(0.2) * t["local"] + 2 * math.exp(-0.7) * t["detector"]
                + 0.3 - 0.2 + 0.7)
    assert math.isclose(out["total"].item(), expected.item(), rel_tol=1e-5)
    out["total"].backward()
    # d/d alpha = 1 - e^-alpha L1, etc.
    assert math.isclose(loss.alpha.grad.item(), 1 - math.exp(-0.3) * t["global"].item(), rel_tol=1e-4)
    assert math.isclose(loss.beta.grad.item(), 1 - math.exp(0.2) * t["local"].item(), rel_tol=1e-4)
    assert math.isclose(loss.gamma.grad.item(), 1 - 2 * math.exp(-0.7) * t["detector"].item(), rel_tol=1e-4)
    for key in ("alpha", "beta", "gamma"):
        assert key in out
