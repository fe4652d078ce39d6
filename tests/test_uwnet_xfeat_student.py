"""The XFeat student: step 0 reproduces the XFeat teacher; export/load by architecture; trains through configs."""

import numpy as np
import pytest
import torch
from conftest import compose

from ruslam import load_extractor
from ruslam.models.export import export_weights, load_uwnet
from ruslam.models.pretrained.vlad import PACKAGED_XFEAT_CODEBOOK, VLAD
from ruslam.models.pretrained.xfeat import XFeatTeacher
from ruslam.models.uwnet_xfeat_student import XFeatStudent, with_teacher_detector, without_descriptor_residual
from ruslam.train import train


def _images(h=72, w=104, n=2):  # not multiples of 32: the student must pad exactly as the teacher does
    g = torch.Generator().manual_seed(0)
    base = torch.rand(n, 3, h // 8, w // 8, generator=g)
    return (torch.nn.functional.interpolate(base, size=(h, w), mode="bilinear") + 0.1 * torch.rand(n, 3, h, w,
                                                                                                     generator=g)) / 1.1


@pytest.mark.parametrize("mode", ["eval", "train"])
@pytest.mark.parametrize("neighbourhood", [False, True])
def test_step_zero_outputs_equal_the_xfeat_teacher(mode, neighbourhood):
    student, teacher = XFeatStudent(keypoint_neighbourhood=neighbourhood), XFeatTeacher()
    student.train(mode == "train")
    x = _images()
    with torch.no_grad():
        got, want = student(x), teacher(x)
        vlad = VLAD(64, 64, codebook=str(PACKAGED_XFEAT_CODEBOOK))(x, want)
    assert got["keypoint_logits"].shape == want["keypoint_logits"].shape == (2, 65, 9, 13)
    assert (got["keypoint_logits"] - want["keypoint_logits"]).abs().max() < 1e-4
    assert (got["dense_descriptors"] - want["dense_descriptors"]).abs().max() < 1e-4
    # The NetVLAD head starts near the teacher's hard VLAD (same codebook, sharp soft assignment).
    assert (got["global_descriptor"] * vlad).sum(-1).min() > 0.9


def test_added_blocks_are_trainable_and_move_the_outputs():
    student = XFeatStudent(keypoint_neighbourhood=True)
    x = _images(n=1)
    out = student(x)
    (out["keypoint_logits"].pow(2).mean() + out["dense_descriptors"].sum()).backward()
    for name in ("kp_context.weight", "kp_neighbours.weight", "deform.3.conv.weight", "attention.position.gamma"):
        grad = dict(student.named_parameters())[name].grad
        assert grad is not None and grad.abs().sum() > 0, name


def test_export_and_load_extractor_round_trip(tmp_path):
    student = XFeatStudent()
    with torch.no_grad():
        student.kp_context.weight.normal_(0, 0.01)  # not the teacher any more: loading must keep this
    path = export_weights(student, tmp_path / "student.pt")
    loaded = load_uwnet(path)
    assert isinstance(loaded, XFeatStudent)
    assert torch.allclose(loaded.kp_context.weight, student.kp_context.weight.half().float())
    image = (np.random.default_rng(0).random((96, 128, 3)) * 255).astype(np.uint8)
    out = load_extractor(path).extract(image)
    assert out["descriptors"].shape[1] == 64 and out["global_descriptor"].shape == (4096,)
    assert len(out["keypoints"]) > 0


def test_fine_tuning_may_add_the_keypoint_neighbourhood_block_only(tmp_path):
    from ruslam.errors import InputError
    from ruslam.training.common import load_initial_weights

    start = XFeatStudent()
    with torch.no_grad():
        start.kp_context.weight.normal_(0, 0.01)
    path = export_weights(start, tmp_path / "start.pt")
    grown = XFeatStudent(keypoint_neighbourhood=True)
    load_initial_weights(grown, path)  # the new block stays zero: the same function as the file
    assert torch.allclose(grown.kp_context.weight, start.kp_context.weight.half().float())
    assert grown.kp_neighbours.weight.abs().sum() == 0
    x = _images(n=1)
    with torch.no_grad():
        assert (grown.eval()(x)["keypoint_logits"] - load_uwnet(path).eval()(x)["keypoint_logits"]).abs().max() < 1e-5
    with pytest.raises(InputError, match="attention"):  # another change of architecture is still refused
        load_initial_weights(XFeatStudent(keypoint_neighbourhood=True, attention=False), path)


def test_teacher_detector_restores_xfeat_keypoints_and_keeps_trained_descriptors(tmp_path):
    student = XFeatStudent().eval()
    with torch.no_grad():  # a "trained" student: every added block and the keypoint head moved away from XFeat
        for name, p in student.named_parameters():
            if name.startswith(("kp_context", "attention", "deform.3", "xfeat.keypoint_head", "xfeat.block_fusion")):
                p.add_(torch.randn_like(p) * 0.05)
    x = _images()
    reset = with_teacher_detector(student).eval()
    assert reset.config["attention"] is False
    with torch.no_grad():
        got, trained, want = reset(x), student(x), XFeatTeacher()(x)
    assert (trained["keypoint_logits"] - want["keypoint_logits"]).abs().max() > 1e-2  # the premise: it moved
    assert (got["keypoint_logits"] - want["keypoint_logits"]).abs().max() < 1e-4
    assert torch.allclose(got["dense_descriptors"], trained["dense_descriptors"], atol=1e-6)
    assert torch.allclose(got["global_descriptor"], trained["global_descriptor"], atol=1e-6)
    loaded = load_uwnet(export_weights(reset, tmp_path / "reset.pt"))  # the file rebuilds without attention
    assert loaded.config["attention"] is False


def test_without_descriptor_residual_keeps_everything_but_the_dcn_block(tmp_path):
    student = XFeatStudent().eval()
    with torch.no_grad():
        for name, p in student.named_parameters():
            if name.startswith(("deform", "xfeat.block_fusion", "kp_context")):
                p.add_(torch.randn_like(p) * 0.05)
    x = _images()
    pruned = without_descriptor_residual(student).eval()
    assert pruned.deform is None and not any(k.startswith("deform.") for k in pruned.state_dict())
    with torch.no_grad():
        got, trained = pruned(x), student(x)
        for p in student.deform[3].parameters():  # the same network with the residual switched off
            p.zero_()
        want = student(x)
    assert (trained["dense_descriptors"] - want["dense_descriptors"]).abs().max() > 1e-3  # the block did act
    assert torch.allclose(got["dense_descriptors"], want["dense_descriptors"], atol=1e-6)
    assert torch.allclose(got["keypoint_logits"], trained["keypoint_logits"], atol=1e-6)
    loaded = load_uwnet(export_weights(pruned, tmp_path / "pruned.pt"))
    assert loaded.deform is None and loaded.config["descriptor_residual"] is False
    # Without the block nothing is deformable: the file's config says so (it asked for deformable=True).
    assert student.config["deformable"] is True and loaded.config["deformable"] is False
    assert XFeatStudent(descriptor_residual=False, deformable=True).config["deformable"] is False


def test_step_zero_extractor_ranks_keypoints_as_xfeat(tmp_path):
    """Top-k after XFeat's reliability weighting: with only 60 of the candidates kept, the ranking decides which."""
    path = export_weights(XFeatStudent().eval(), tmp_path / "step0.pt")
    rng = np.random.default_rng(1)
    image = (np.kron(rng.random((12, 16, 3)), np.ones((16, 16, 1))) * 0.7 + rng.random((192, 256, 3)) * 0.3)
    image = (image * 255).astype(np.uint8)
    student = load_extractor(path, max_keypoints=60, detection_threshold=0.05, subpixel_radius=0,
                             resize_min=None, min_pixels=None).extract(image)  # XFeat runs at the input size
    xfeat = load_extractor("xfeat", max_keypoints=60).extract(image)
    same = {tuple(p) for p in np.round(student["keypoints"]).astype(int)} & {
        tuple(p) for p in np.round(xfeat["keypoints"]).astype(int)}
    assert len(same) >= 57, len(same)


def test_student_rejects_other_widths():
    with pytest.raises(ValueError, match="64-d descriptors"):
        XFeatStudent(descriptor_dim=128)


def _tiny_training(tmp_path, init_weights, *overrides):
    """The training config on 6 tiny procedural images, starting from `init_weights`, plus `overrides`."""
    return compose("train", [f"out_dir={tmp_path}", f"datamodule.cache_root={tmp_path / 'cache'}",
                             "model=uwnet_xfeat_student", "data.num_images=6", "data.height=64", "data.width=96",
                             "datamodule.image_size=null", "datamodule.val_size=2", "datamodule.batch_size=2",
                             "datamodule.num_workers=0", f"teacher.global_head.codebook={PACKAGED_XFEAT_CODEBOOK}",
                             "trainer.enable_progress_bar=false", "~callbacks.progress_bar",
                             f"init_weights={init_weights}", *overrides])


def test_student_trains_through_the_composed_config(tmp_path):
    start = export_weights(XFeatStudent(vlad_codebook=str(PACKAGED_XFEAT_CODEBOOK)), tmp_path / "start.pt")
    cfg = _tiny_training(tmp_path, start, "+trainer.fast_dev_run=true", "model.net.frozen_batchnorm=true")
    assert train(cfg) is not None
    trained = load_uwnet(tmp_path / "uwnet.pt")
    assert isinstance(trained, XFeatStudent)
    # XFeat's batch norms keep their statistics through a Lightning fit (Lightning bypasses the student's train()).
    before, after = load_uwnet(start).state_dict(), trained.state_dict()
    stats = [k for k in before if k.startswith("xfeat.") and "running_" in k]
    assert stats and all(torch.equal(before[k], after[k]) for k in stats)


def test_unfrozen_batchnorm_updates_xfeat_statistics():
    student = XFeatStudent(frozen_batchnorm=False).train()
    before = {k: v.clone() for k, v in student.state_dict().items() if "running_mean" in k}
    with torch.no_grad():
        student(_images())
    assert any(not torch.equal(before[k], student.state_dict()[k]) for k in before if k.startswith("xfeat.block"))
    assert XFeatStudent().train().xfeat.block1[0].layer[1].training is False


def test_training_only_the_reliability_head_changes_nothing_else(tmp_path):
    start = export_weights(XFeatStudent(vlad_codebook=str(PACKAGED_XFEAT_CODEBOOK)), tmp_path / "start.pt")
    cfg = _tiny_training(tmp_path, start, "trainer.max_epochs=1", "model.reliability_weight=1.0",
                         "model.trainable=[xfeat.heatmap_head.]", "model.optimizer.lr=0.01")
    train(cfg)
    before = load_uwnet(start).state_dict()
    after = load_uwnet(tmp_path / "uwnet.pt").state_dict()
    changed = {k for k in before if (before[k].float() - after[k].float()).abs().max() > 1e-2}
    assert changed and all(k.startswith("xfeat.heatmap_head.") for k in changed), sorted(changed)[:5]
    metrics = (tmp_path / "csv" / "version_0" / "metrics.csv").read_text()
    assert "val/reliability" in metrics


def test_trainable_must_name_parameters():
    from ruslam.errors import InputError
    from ruslam.training.module import DistillationModule

    with pytest.raises(InputError, match="model.trainable"):
        DistillationModule(XFeatStudent(), torch.optim.Adam, trainable=["backbone."])


def test_reliability_loss_trains_the_reliability_head_only():
    from ruslam.models.correspondence_loss import CorrespondenceLoss
    from ruslam.models.reliability_loss import ReliabilityLoss

    student = XFeatStudent().train()
    x = _images(n=1)
    out = student(torch.cat([x, x]))
    desc_a, desc_b = out["dense_descriptors"].chunk(2)
    samples = CorrespondenceLoss().sample(desc_a, desc_b, torch.eye(3)[None])
    ReliabilityLoss()(out["reliability"].chunk(2)[0], samples).backward()
    grads = {k: p.grad for k, p in student.named_parameters()}
    assert any(g is not None and g.abs().sum() > 0 for k, g in grads.items() if k.startswith("xfeat.heatmap_head."))
    assert all(g is None or g.abs().sum() == 0 for k, g in grads.items() if not k.startswith("xfeat.heatmap_head."))
