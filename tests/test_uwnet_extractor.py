"""UWNet behind the extractor contract: export/load round trip, outputs, bad inputs with one clear sentence."""

import numpy as np
import pytest
import torch
from conftest import assert_same_global_descriptor

from ruslam import load_extractor
from ruslam.models.export import export_weights, load_uwnet
from ruslam.models.uwnet import UWNet
from ruslam.models.uwnet_extractor import UWNetExtractor


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    torch.manual_seed(0)
    net = UWNet(descriptor_dim=64, head_channels=16, vlad_dim=8)
    with torch.no_grad():  # non-trivial BN statistics so the round trip checks buffers too
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    path = tmp_path_factory.mktemp("w") / "uwnet.pt"
    export_weights(net, path)
    return path, net.eval()


def test_export_is_fp16_weights_only_and_round_trips(weights):
    path, net = weights
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == "ruslam-uwnet"
    assert all(v.dtype == torch.float16 for v in raw["state_dict"].values() if v.is_floating_point())
    loaded = load_uwnet(path)
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        a, b = net(x), loaded(x)
    for key in a:  # fp16 storage: close, not bit-equal
        torch.testing.assert_close(a[key], b[key], atol=2e-2, rtol=2e-2)


def test_extract_contract_and_resize_mapping(weights):
    path, _ = weights
    ext = load_extractor(path, max_keypoints=50, detection_threshold=0.0, min_pixels=None, resize_max=None)
    img = (np.random.default_rng(0).random((96, 128, 3)) * 255).astype(np.uint8)
    out = ext.extract(img)
    n = len(out["keypoints"])
    assert n == 50 and out["scores"].shape == (n,) and out["descriptors"].shape == (n, 64)
    assert out["global_descriptor"].shape == (4096,)
    np.testing.assert_allclose(np.linalg.norm(out["descriptors"], axis=1), 1.0, rtol=1e-4)
    kp = out["keypoints"]
    assert (kp >= 0).all() and (kp[:, 0] <= 127).all() and (kp[:, 1] <= 95).all()
    # Grey float input works; an image twice the size, resized back by resize_max, gives keypoints twice as far.
    assert ext.extract(img.mean(axis=2).astype(np.float32) / 255)["descriptors"].shape[1] == 64
    big = np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)
    opts = {"max_keypoints": 0, "detection_threshold": 0.002, "subpixel_radius": 0}  # integer pixels: exact
    small = UWNetExtractor.from_file(path, min_pixels=None, resize_max=None, **opts).extract(img)
    big_kp = UWNetExtractor.from_file(path, min_pixels=None, resize_max=128, **opts).extract(big)
    expected = (small["keypoints"] + 0.5) * 2 - 0.5
    assert len(expected) > 5
    np.testing.assert_allclose(np.unique(big_kp["keypoints"], axis=0), np.unique(expected, axis=0), atol=1e-4)


def test_missing_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        UWNetExtractor.from_file(tmp_path / "nope.pt")


def test_checkpoint_of_another_architecture(tmp_path):
    path = tmp_path / "other.pt"
    torch.save(torch.nn.Linear(3, 4).state_dict(), path)
    with pytest.raises(ValueError, match="is not a UWNet weights file"):
        UWNetExtractor.from_file(path)
    wrong = tmp_path / "wrong_shapes.pt"
    export_weights(UWNet(head_channels=16, vlad_dim=8), wrong)
    raw = torch.load(wrong, weights_only=True)
    raw["config"]["head_channels"] = 32
    torch.save(raw, wrong)
    with pytest.raises(ValueError, match="does not match the UWNet architecture"):
        UWNetExtractor.from_file(wrong)


def test_checkpoint_of_another_descriptor_width(weights):
    with pytest.raises(ValueError, match="has 64-d descriptors, but 256-d were requested"):
        UWNetExtractor.from_file(weights[0], descriptor_dim=256)


@pytest.mark.parametrize(("image", "message"), [
    (np.zeros((64, 64, 3), np.int32), "dtype int32"),
    (np.zeros((64, 64, 4), np.uint8), "HxW or HxWx3"),
    (np.full((64, 64), np.nan, np.float32), "NaN"),
])
def test_bad_images(weights, image, message):
    ext = UWNetExtractor.from_file(weights[0])
    with pytest.raises(ValueError, match=message):
        ext.extract(image)


def test_onnx_export_matches_pytorch_under_onnxruntime(tmp_path, weights):
    ort = pytest.importorskip("onnxruntime")
    from ruslam.models.export import ONNX_OUTPUTS, export_onnx

    net = load_uwnet(weights[0])
    with torch.no_grad():  # learned (non-zero) offsets so the DCN sampling path is really exercised
        for m in net.modules():
            if hasattr(m, "offset") and isinstance(m.offset, torch.nn.Conv2d):
                m.offset.weight.normal_(0, 0.3)
    path = export_onnx(net, tmp_path / "uwnet.onnx", height=64, width=96)
    x = torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        ref = net(x)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    outs = session.run(list(ONNX_OUTPUTS), {"image": x.numpy()})
    for name, value in zip(ONNX_OUTPUTS, outs, strict=True):
        if name == "global_descriptor":
            assert_same_global_descriptor(value, ref[name].numpy())
        else:
            np.testing.assert_allclose(value, ref[name].numpy(), atol=1e-4, rtol=1e-3)


def test_shipped_checkpoint_loads_by_name_and_is_small_fp16():
    from ruslam.models.uwnet_extractor import SHIPPED_WEIGHTS

    assert SHIPPED_WEIGHTS.stat().st_size <= 10 * 1024 * 1024
    raw = torch.load(SHIPPED_WEIGHTS, weights_only=True)
    assert all(v.dtype == torch.float16 for v in raw["state_dict"].values() if v.is_floating_point())
    out = load_extractor("uwnet_xfeat").extract(np.zeros((120, 160, 3), np.uint8) + 128)
    assert out["global_descriptor"].shape == (4096,) and out["descriptors"].shape[1] == 64


def test_resize_min_equals_upsampling_by_hand(weights):
    """resize_min runs the network on the upsampled image and maps keypoints back to input pixels: the same
    keypoints and descriptors as upsampling by hand (bilinear, half-pixel centres), x = (x' + 0.5) / 2 - 0.5."""
    path, _ = weights
    rgb = np.random.default_rng(1).random((96, 128, 3)).astype(np.float32)
    up = torch.nn.functional.interpolate(torch.from_numpy(rgb).permute(2, 0, 1)[None], size=(192, 256),
                                         mode="bilinear", align_corners=False)[0].permute(1, 2, 0).numpy()
    opts = {"max_keypoints": 0, "detection_threshold": 0.002, "subpixel_radius": 0}
    small = UWNetExtractor.from_file(path, min_pixels=None, resize_min=256, **opts).extract(rgb)
    by_hand = UWNetExtractor.from_file(path, min_pixels=None, resize_max=None, **opts).extract(np.ascontiguousarray(up))
    native = UWNetExtractor.from_file(path, min_pixels=None, resize_max=None, **opts).extract(rgb)
    assert len(small["keypoints"]) == len(by_hand["keypoints"]) > len(native["keypoints"]) > 5  # finer cells
    a, b = np.lexsort(small["keypoints"].T), np.lexsort(by_hand["keypoints"].T)  # equal scores: any order
    np.testing.assert_allclose(small["keypoints"][a], (by_hand["keypoints"][b] + 0.5) / 2 - 0.5, atol=1e-4)
    np.testing.assert_allclose(small["descriptors"][a], by_hand["descriptors"][b], atol=1e-4)
    assert small["keypoints"].max(0).tolist() < [128, 96] and small["keypoints"].min() > -0.5


def test_working_size_is_an_area_that_never_shrinks_a_frame(weights):
    """min_pixels: a 640x480 frame runs at 672x504's area, a wide 1240x376 frame (more pixels than that) at its own
    resolution instead of being shrunk to a 672 px longer side, a small 320x240 one upsampled with its aspect."""
    ext = UWNetExtractor.from_file(weights[0])
    assert ext._input_size(480, 640) == (504, 672)
    assert ext._input_size(376, 1240) == (376, 1240)
    h, w = ext._input_size(240, 320)
    assert (h, w) == (504, 672) and h * w >= 0.97 * 672 * 504
    with pytest.raises(ValueError, match="min_pixels"):
        UWNetExtractor.from_file(weights[0], min_pixels=-1)


@pytest.mark.parametrize("key", ["resize_min", "resize_max"])
@pytest.mark.parametrize("size", [0, -640, "640", 10**6])
def test_resize_options_reject_what_is_not_a_size(weights, key, size):
    with pytest.raises(ValueError, match=key):
        UWNetExtractor.from_file(weights[0], **{key: size})
