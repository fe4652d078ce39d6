import pickle

import numpy as np
import pytest
import torch
import torch.nn as nn

from ruslam import load_extractor
from ruslam.models.pretrained.superpoint import SuperPoint, SuperPointTeacher
from ruslam.models.weights import resolve_weights, sha256_of

# Key names and shapes of magicleap/SuperPointPretrainedNetwork superpoint_v1.pth (from its demo_superpoint.py).
MAGICLEAP = {
    "conv1a": (64, 1, 3), "conv1b": (64, 64, 3), "conv2a": (64, 64, 3), "conv2b": (64, 64, 3),
    "conv3a": (128, 64, 3), "conv3b": (128, 128, 3), "conv4a": (128, 128, 3), "conv4b": (128, 128, 3),
    "convPa": (256, 128, 3), "convPb": (65, 256, 1), "convDa": (256, 128, 3), "convDb": (256, 256, 1),
}


def magicleap_state_dict(seed=0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    state = {}
    for name, (cout, cin, k) in MAGICLEAP.items():
        state[f"{name}.weight"] = torch.randn(cout, cin, k, k, generator=g) * (2.0 / (cin * k * k)) ** 0.5
        state[f"{name}.bias"] = torch.randn(cout, generator=g) * 0.01
    return state


@pytest.fixture
def weights_file(tmp_path):
    path = tmp_path / "superpoint_v1.pth"
    torch.save(magicleap_state_dict(), path)
    return path


def test_magicleap_state_dict_loads_strictly(weights_file):
    sp = load_extractor("superpoint", weights=str(weights_file))
    loaded = sp.net.state_dict()
    reference = magicleap_state_dict()
    assert set(loaded) == set(reference)
    for k, v in reference.items():
        assert torch.equal(loaded[k], v), k


def test_wrapped_checkpoint_is_accepted(tmp_path):
    path = tmp_path / "wrapped.pth"
    torch.save({"state_dict": magicleap_state_dict(1), "epoch": 3}, path)
    assert torch.equal(SuperPoint(weights=str(path)).net.convDb.bias, magicleap_state_dict(1)["convDb.bias"])


def test_mismatched_weights_name_the_keys(tmp_path):
    state = magicleap_state_dict()
    del state["convDb.bias"]
    state["conv5.weight"] = torch.zeros(1)
    state["convPb.weight"] = torch.zeros(64, 256, 1, 1)
    path = tmp_path / "bad.pth"
    torch.save(state, path)
    with pytest.raises(ValueError) as err:
        SuperPoint(weights=str(path))
    msg = str(err.value)
    assert "missing keys ['convDb.bias']" in msg and "unexpected keys ['conv5.weight']" in msg
    assert "convPb.weight (64, 256, 1, 1) (expected (65, 256, 1, 1))" in msg and str(path) in msg


class Pickled:
    pass


def test_non_weights_file_is_refused_without_unpickling(tmp_path):
    path = tmp_path / "evil.pth"
    with open(path, "wb") as f:
        pickle.dump(Pickled(), f)
    with pytest.raises(ValueError, match="not a readable weights-only torch checkpoint"):
        SuperPoint(weights=str(path))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        SuperPoint(weights=str(tmp_path / "absent.pth"))


def test_missing_default_weights_say_where_to_put_them(tmp_path, monkeypatch):
    monkeypatch.setenv("RUSLAM_CACHE", str(tmp_path))
    with pytest.raises(FileNotFoundError, match=f"put the file at {tmp_path}/weights/superpoint_v1.pth"):
        load_extractor("superpoint")


def test_url_download_checks_sha256_and_reports_offline(tmp_path, weights_file):
    url, digest, cache = weights_file.as_uri(), sha256_of(weights_file), tmp_path / "cache"
    with pytest.raises(ValueError, match="has sha256"):
        resolve_weights(url, sha256="0" * 64, cache_dir=cache)
    assert list(cache.iterdir()) == []  # the mismatching download was not kept
    got = resolve_weights(url, sha256=digest, cache_dir=cache)
    assert got == cache / "superpoint_v1.pth" and sha256_of(got) == digest
    weights_file.unlink()  # cached now: no second download
    assert resolve_weights(url, sha256=digest, cache_dir=cache) == got
    with pytest.raises(OSError, match=f"put it at {cache}/other.pth"):
        resolve_weights("http://127.0.0.1:9/other.pth", cache_dir=cache)
    assert sorted(p.name for p in cache.iterdir()) == ["superpoint_v1.pth"]


class PeakNet(nn.Module):
    """Fake SuperPoint head: one confident keypoint at pixel (x=21, y=13), descriptor = its cell's index."""

    def forward(self, grey):
        b, _, h, w = grey.shape
        logits = torch.full((b, 65, h // 8, w // 8), -10.0)
        logits[:, 64] = 10.0
        logits[:, 8 * 5 + 5, 1, 2] = 10.0  # cell row 1, col 2; inside the cell row 5, col 5
        logits[:, 64, 1, 2] = -10.0
        ys, xs = torch.meshgrid(torch.arange(h // 8.0), torch.arange(w // 8.0), indexing="ij")
        desc = torch.stack([xs, ys, torch.ones_like(xs)])[None].expand(b, -1, -1, -1)
        return logits, desc


def test_post_processing_finds_the_peak_and_samples_its_cell():
    out = SuperPoint(net=PeakNet(), border=4).extract(np.zeros((50, 70), np.uint8))  # padded to 56x72 inside
    assert out["keypoints"].tolist() == [[21.0, 13.0]] and out["scores"][0] > 0.99
    # pixel (21, 13) is the centre-ish of cell (col 2, row 1): (21 + .5) / 8 - .5 = 2.1875, (13 + .5) / 8 - .5 = 1.1875
    expect = np.array([2.1875, 1.1875, 1.0]) / np.linalg.norm([2.1875, 1.1875, 1.0])
    np.testing.assert_allclose(out["descriptors"][0], expect, atol=1e-5)


def test_teacher_converts_rgb_to_bt601_grey(weights_file):
    sp = SuperPoint(weights=str(weights_file))
    teacher = SuperPointTeacher(net=sp.net)
    rgb = torch.rand(1, 3, 32, 48, generator=torch.Generator().manual_seed(0))
    out = teacher(rgb)
    grey = 0.299 * rgb[:, :1] + 0.587 * rgb[:, 1:2] + 0.114 * rgb[:, 2:]
    logits, desc = sp.net(grey)
    torch.testing.assert_close(out["keypoint_logits"], logits)
    torch.testing.assert_close(out["dense_descriptors"], torch.nn.functional.normalize(desc, dim=1))
    assert out["dense_descriptors"].shape == (1, 256, 4, 6)
    with pytest.raises(ValueError, match="multiples of 8"):
        teacher(torch.rand(1, 3, 30, 48))
