"""UWNet with 4x4 keypoint cells: the start equals the 8x8 file pixel for pixel; it trains; the online trainer runs."""

import json

import numpy as np
import pytest
import torch
from conftest import compose

from ruslam import load_extractor
from ruslam.models.distillation_loss import DistillationLoss
from ruslam.models.export import export_weights, load_uwnet
from ruslam.models.extractor import cell_logits_to_heatmap, decode_sparse
from ruslam.models.uwnet_extractor import SHIPPED_WEIGHTS, UWNetExtractor
from ruslam.models.uwnet_xfeat_student import XFeatStudent, subcell_logits, subcell_targets
from ruslam.train import train
from ruslam.training.common import load_initial_weights


def _images(h=72, w=104, n=2):
    g = torch.Generator().manual_seed(0)
    base = torch.rand(n, 3, h // 8, w // 8, generator=g)
    return (torch.nn.functional.interpolate(base, size=(h, w), mode="bilinear") + 0.1 * torch.rand(n, 3, h, w,
                                                                                                     generator=g)) / 1.1


def _grown(path=SHIPPED_WEIGHTS) -> XFeatStudent:
    config = {k: v for k, v in load_uwnet(path).config.items() if k != "architecture"}
    net = XFeatStudent(**config, keypoint_cell=4, teacher_weights="none")
    load_initial_weights(net, path)
    return net.eval()


def test_subcell_logits_keep_the_heat_map_and_every_softmax():
    logits = torch.randn(2, 65, 3, 5) * 4
    sub = subcell_logits(logits, 4)
    assert sub.shape == (2, 17, 6, 10)
    torch.testing.assert_close(cell_logits_to_heatmap(sub), cell_logits_to_heatmap(logits), atol=1e-6, rtol=1e-5)
    assert cell_logits_to_heatmap(sub).shape == (2, 24, 40)
    t, mask = subcell_targets(logits, torch.ones(2, 3, 5), 4)
    assert t.shape == (2, 17, 6, 10) and mask.shape == (2, 6, 10)
    assert subcell_logits(logits, 8) is logits


def test_the_finer_student_starts_as_the_shipped_file():
    shipped, fine = load_uwnet(SHIPPED_WEIGHTS), _grown()
    assert fine.config["keypoint_cell"] == 4 and "keypoint_cell" not in shipped.config
    x = _images()
    with torch.no_grad():
        a, b = shipped(x), fine(x)
    assert b["keypoint_logits"].shape == (2, 17, 18, 26)
    heat_a, heat_b = cell_logits_to_heatmap(a["keypoint_logits"]), cell_logits_to_heatmap(b["keypoint_logits"])
    assert (heat_a - heat_b).abs().max() < 1e-6
    for key in ("dense_descriptors", "global_descriptor", "reliability"):
        torch.testing.assert_close(a[key], b[key])


def test_same_keypoints_at_the_start_and_a_file_round_trip(tmp_path):
    path = export_weights(_grown(), tmp_path / "s4.pt")
    rng = np.random.default_rng(0)
    image = np.full((120, 160, 3), 60, np.uint8)
    for _ in range(40):  # bright squares: corners to detect
        x, y, s = rng.integers(0, 140), rng.integers(0, 100), rng.integers(4, 20)
        image[y:y + s, x:x + s] = rng.integers(100, 255)
    opts = {"resize_min": None, "resize_max": None, "detection_threshold": 1e-4}
    want = UWNetExtractor(**opts).extract(image)
    got = load_extractor(path, **opts).extract(image)
    assert len(want["keypoints"]) > 10 and len(got["keypoints"]) == len(want["keypoints"])
    order = [np.lexsort((out["keypoints"][:, 0], out["keypoints"][:, 1])) for out in (got, want)]  # equal scores
    np.testing.assert_allclose(got["keypoints"][order[0]], want["keypoints"][order[1]], atol=1e-3)
    np.testing.assert_allclose(got["descriptors"][order[0]], want["descriptors"][order[1]], atol=1e-3)


def test_decode_reads_the_cell_off_the_logits():
    logits = torch.full((1, 17, 4, 6), -10.0)
    logits[0, 5, 1, 2] = 10.0  # 4x4 cell (1, 2), pixel row 1, column 1 -> pixel (x, y) = (9, 5)
    conf = {"nms_radius": 2, "detection_threshold": 0.1, "max_keypoints": 10, "border": 0}
    xy, scores, desc = decode_sparse(logits, torch.randn(1, 8, 2, 3), (16, 24), conf, 8)
    assert xy.tolist() == [[9.0, 5.0]] and desc.shape == (1, 8)


def test_the_fine_branch_learns_and_the_loss_takes_the_8x8_targets():
    fine = _grown().train()
    params = [p for n, p in fine.named_parameters() if n.startswith("kp_fine_")]
    x = _images(n=2)
    with torch.no_grad():
        target = {k: v.float() for k, v in load_uwnet(SHIPPED_WEIGHTS).eval()(x).items()}
        target["keypoint_logits"] = torch.randn_like(target["keypoint_logits"]) * 3
    loss = DistillationLoss()
    first = loss.terms(fine(x), target, torch.ones(2, 9, 13))["detector"]
    first.backward()
    assert all(p.grad is not None for p in params) and params[-1].grad.abs().sum() > 0
    opt = torch.optim.Adam(params, lr=1e-2)
    for _ in range(20):
        opt.zero_grad()
        loss.terms(fine(x), target, torch.ones(2, 9, 13))["detector"].backward()
        opt.step()
    assert loss.terms(fine(x), target, torch.ones(2, 9, 13))["detector"] < first - 0.05


@pytest.mark.parametrize("teacher", ["xfeat_vlad"])
def test_online_training_rehearsal(tmp_path, teacher):
    cfg = compose("train", ["experiment=fine_cells", f"teacher={teacher}", f"out_dir={tmp_path}",
                            f"init_weights={SHIPPED_WEIGHTS}", "online.max_steps=2", "online.log_every=1",
                            "datamodule.limit_images=6", "datamodule.val_size=2", "datamodule.batch_size=2",
                            "datamodule.image_size=[64,96]", "data.height=64", "data.width=96", "torch_threads=1"])
    final = train(cfg)
    report = json.loads((tmp_path / "online_losses.json").read_text())
    assert report["steps"] == 2 and report["device"] == "cpu" and np.isfinite(final)
    assert set(report["held_out_before"]) >= {"detector", "local", "global", "correspondence", "total"}
    net = load_uwnet(tmp_path / "uwnet_xfeat_s4.pt")
    assert net.config["keypoint_cell"] == 4


def test_upsampled_cells_are_the_2x_detector_at_1x():
    from ruslam.models.uwnet_xfeat_student import upsampled_cells

    logits = torch.randn(1, 65, 3, 4) * 3
    target = upsampled_cells(logits, 4)
    assert target.shape == (1, 17, 3, 4)
    heat2x = cell_logits_to_heatmap(logits)  # [1, 24, 32] of the 2x image
    pooled = torch.nn.functional.avg_pool2d(heat2x[:, None], 2)[:, 0] * 4  # its probability per 1x pixel
    torch.testing.assert_close(cell_logits_to_heatmap(target), pooled, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(target.exp().sum(1), torch.ones(1, 3, 4))


def test_batched_target_warp_equals_the_per_image_one():
    from ruslam.training.augment import GeometricAugment, seeded_generator, warp_targets, warp_targets_batch

    g = torch.Generator().manual_seed(0)
    targets = {"keypoint_logits": torch.randn(3, 65, 6, 8, generator=g) * 3,
               "dense_descriptors": torch.nn.functional.normalize(torch.randn(3, 64, 6, 8, generator=g), dim=1),
               "global_descriptor": torch.randn(3, 16, generator=g)}
    homs = torch.stack([GeometricAugment().sample(48, 64, seeded_generator(0, i)) for i in range(3)])
    batch = warp_targets_batch(targets, homs)
    for i in range(3):
        one = warp_targets({k: v[i] for k, v in targets.items()}, homs[i])
        for key in ("keypoint_logits", "dense_descriptors", "mask", "global_descriptor"):
            torch.testing.assert_close(batch[key][i], one[key], atol=1e-5, rtol=1e-4)
