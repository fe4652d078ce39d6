"""hloc's files (`python -m ruslam.features`), read back by a reader written here to hloc's conventions, the torch
module and its ONNX decode, and the docs/pipelines.md examples."""

from __future__ import annotations

import re

import cv2
import h5py
import numpy as np
import pytest
import torch
from conftest import ROOT, assert_same_global_descriptor

from ruslam.errors import InputError
from ruslam.features.__main__ import main as features_main
from ruslam.features.pipeline import extract_features, list_images, make_pairs
from ruslam.models.extractor import Extractor
from ruslam.models.registry import load_extractor

# --------------------------------------------------------------- a reader written to hloc's conventions (no ruslam)


def hloc_pair_name(name0: str, name1: str) -> str:  # hloc.utils.parsers.names_to_pair (current, '/' separator)
    return "/".join((name0.replace("/", "-"), name1.replace("/", "-")))


def hloc_keypoints(path, name):  # hloc.utils.io.get_keypoints
    with h5py.File(path, "r") as fd:
        return fd[name]["keypoints"].__array__()


def hloc_matches(path, name0, name1):  # hloc.utils.io.get_matches
    with h5py.File(path, "r") as fd:
        pair = hloc_pair_name(name0, name1)
        m0 = fd[pair]["matches0"].__array__()
        s0 = fd[pair]["matching_scores0"].__array__()
    idx = np.where(m0 != -1)[0]
    return np.stack([idx, m0[idx]], -1), s0[idx]


# -------------------------------------------------------------------------------------------------- images


def textured(h=240, w=320, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.random((h // 8, w // 8)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5)
    image = np.clip(0.6 * base + 0.8 * (fine - 0.5) + 0.2, 0, 1)
    return (np.stack([image * 0.5, image, image * 0.8], -1) * 255).astype(np.uint8)


SHIFT = np.array([12.0, -7.0])  # image b is image a moved by this (pixels)


@pytest.fixture
def image_dir(tmp_path):
    """a.png, sub/b.png (a shifted) and c.png: names with a folder, a known motion between the first two."""
    root = tmp_path / "images"
    (root / "sub").mkdir(parents=True)
    a = textured()
    M = np.float32([[1, 0, SHIFT[0]], [0, 1, SHIFT[1]]])
    cv2.imwrite(str(root / "a.png"), a[..., ::-1])
    cv2.imwrite(str(root / "sub" / "b.png"), cv2.warpAffine(a, M, (320, 240), borderMode=cv2.BORDER_REFLECT)[..., ::-1])
    cv2.imwrite(str(root / "c.png"), textured(seed=1)[..., ::-1])
    (root / "notes.txt").write_text("not an image")
    return root


def test_features_h5_follows_hlocs_layout(image_dir, tmp_path):
    out = tmp_path / "features.h5"
    features_main(["extract", str(image_dir), str(out), "--extractor", "sift", "--max-keypoints", "300"])
    with h5py.File(out, "r") as fd:
        names = []
        fd.visititems(lambda k, o: names.append(k.rsplit("/", 1)[0]) if k.endswith("/keypoints") else None)
        assert sorted(names) == ["a.png", "c.png", "sub/b.png"]
        grp = fd["sub/b.png"]
        assert grp["keypoints"].dtype == np.float32 and grp["keypoints"].shape[1] == 2
        n = grp["keypoints"].shape[0]
        assert 50 < n <= 300
        assert grp["descriptors"].shape == (128, n) and grp["descriptors"].dtype == np.float16
        assert grp["scores"].shape == (n,) and grp["scores"].dtype == np.float16
        assert list(grp["image_size"][()]) == [320, 240]  # (w, h)
        kp = grp["keypoints"][()]
        assert kp.min() >= -0.5 and kp[:, 0].max() <= 319.5 and kp[:, 1].max() <= 239.5


class Centroid(Extractor):
    """One keypoint at the intensity centroid (pixel centres at integer coordinates): an exact detector."""

    def extract(self, image):
        grey = image.astype(np.float64)
        yy, xx = np.mgrid[: grey.shape[0], : grey.shape[1]]
        xy = np.array([[(xx * grey).sum(), (yy * grey).sum()]]) / grey.sum()
        return {"keypoints": xy.astype(np.float32), "scores": np.ones(1, np.float32),
                "descriptors": np.ones((1, 4), np.float32) / 2}


def test_keypoints_use_the_pixel_centre_origin_also_after_resize(tmp_path):
    """A blob centred on pixel (60, 45) is a keypoint at (60, 45), whether or not the image is shrunk first."""
    root = tmp_path / "blob"
    root.mkdir()
    yy, xx = np.mgrid[:120, :160]
    blob = 255 * np.exp(-((xx - 60.0) ** 2 + (yy - 45.0) ** 2) / (2 * 4.0**2))
    cv2.imwrite(str(root / "blob.png"), blob.astype(np.uint8))
    for resize in (None, 80, 64):
        out = tmp_path / f"f{resize}.h5"
        extract_features(root, out, Centroid(), resize_max=resize, progress=False)
        kp = hloc_keypoints(out, "blob.png")
        assert np.abs(kp[0] - [60.0, 45.0]).max() < 0.05, (resize, kp)


def test_pairs_and_matches_read_back_with_hlocs_reader(image_dir, tmp_path):
    feats, pairs, matches = tmp_path / "f.h5", tmp_path / "pairs.txt", tmp_path / "m.h5"
    features_main(["extract", str(image_dir), str(feats), "--extractor", "sift", "--max-keypoints", "500"])
    features_main(["pairs", str(image_dir), str(pairs), "--exhaustive"])
    assert pairs.read_text().split("\n")[:3] == ["a.png c.png", "a.png sub/b.png", "c.png sub/b.png"]
    features_main(["match", str(feats), str(pairs), str(matches), "--ratio", "0.9"])
    with h5py.File(matches, "r") as fd:
        assert "a.png/sub-b.png" in fd  # hloc's names_to_pair: '/' in a name becomes '-', '/' separates
        assert fd["a.png/sub-b.png/matches0"].dtype == np.int16
        assert fd["a.png/sub-b.png/matching_scores0"].dtype == np.float16
    m, s = hloc_matches(matches, "a.png", "sub/b.png")
    k0, k1 = hloc_keypoints(feats, "a.png"), hloc_keypoints(feats, "sub/b.png")
    err = np.linalg.norm(k1[m[:, 1]] - (k0[m[:, 0]] + SHIFT), axis=1)
    assert len(m) > 100 and np.mean(err < 1.0) > 0.95
    assert np.all(s > 0.5)
    unrelated, _ = hloc_matches(matches, "a.png", "c.png")
    assert len(unrelated) < len(m) / 3


def test_an_image_without_keypoints_is_written_and_matched(tmp_path):
    """A blank frame gives ORB no keypoint: its group holds empty arrays of the right shapes, and matching works."""
    root = tmp_path / "blank"
    root.mkdir()
    cv2.imwrite(str(root / "a.png"), np.zeros((64, 64, 3), np.uint8))
    cv2.imwrite(str(root / "b.png"), textured()[..., ::-1])
    feats, pairs, matches = tmp_path / "f.h5", tmp_path / "pairs.txt", tmp_path / "m.h5"
    features_main(["extract", str(root), str(feats), "--extractor", "orb"])
    with h5py.File(feats, "r") as fd:
        assert fd["a.png/keypoints"].shape == (0, 2) and fd["a.png/descriptors"].shape == (32, 0)
        assert fd["b.png/descriptors"].shape[0] == 32 and fd["b.png/descriptors"].shape[1] > 0
    features_main(["pairs", str(root), str(pairs), "--exhaustive"])
    features_main(["match", str(feats), str(pairs), str(matches)])
    assert len(hloc_matches(matches, "a.png", "b.png")[0]) == 0


def test_pairs_sequential_and_retrieval():
    names = [f"{i}.png" for i in range(6)]
    assert make_pairs(names, window=2) == [("0.png", "1.png"), ("0.png", "2.png"), ("1.png", "2.png"),
                                           ("1.png", "3.png"), ("2.png", "3.png"), ("2.png", "4.png"),
                                           ("3.png", "4.png"), ("3.png", "5.png"), ("4.png", "5.png")]
    assert len(make_pairs(names, exhaustive=True)) == 15
    with pytest.raises(InputError, match="Choose a pairing"):
        make_pairs(names)


def test_retrieval_pairs_from_uwnets_global_descriptor(tmp_path):
    """Two scenes, two views each: the nearest image by UWNet's global descriptor is the other view of the scene."""
    root = tmp_path / "scenes"
    root.mkdir()
    for scene in (0, 1):
        image = textured(seed=10 + scene)
        cv2.imwrite(str(root / f"s{scene}_0.png"), image[..., ::-1])
        cv2.imwrite(str(root / f"s{scene}_1.png"), np.roll(image, (6, 9), (0, 1))[..., ::-1])
    feats = tmp_path / "f.h5"
    extract_features(root, feats, load_extractor("uwnet_xfeat", max_keypoints=200, min_pixels=None), progress=False)
    pairs = make_pairs(list_images(root), retrieval=1, features_path=feats)
    assert sorted(pairs) == [("s0_0.png", "s0_1.png"), ("s1_0.png", "s1_1.png")]
    with pytest.raises(InputError, match="global descriptor"):
        extract_features(root, tmp_path / "sift.h5", load_extractor("sift"), progress=False)
        make_pairs(list_images(root), retrieval=1, features_path=tmp_path / "sift.h5")


@pytest.mark.parametrize("case", ["empty", "unreadable", "missing", "unknown pair"])
def test_bad_inputs_one_sentence_exit_2_no_output(case, tmp_path, capsys, image_dir):
    out = tmp_path / "out.h5"
    folder = tmp_path / "bad"
    folder.mkdir()
    if case == "empty":
        (folder / "readme.txt").write_text("no images here")
        argv = ["extract", str(folder), str(out), "--extractor", "sift"]
        expected = "holds no images"
    elif case == "unreadable":
        cv2.imwrite(str(folder / "ok.png"), textured()[..., ::-1])
        (folder / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
        argv = ["extract", str(folder), str(out), "--extractor", "sift"]
        expected = "cannot be decoded as an image"
    elif case == "missing":
        argv = ["extract", str(tmp_path / "nowhere"), str(out), "--extractor", "sift"]
        expected = "does not exist"
    else:
        feats = tmp_path / "f.h5"
        features_main(["extract", str(image_dir), str(feats), "--extractor", "sift", "--max-keypoints", "50"])
        (tmp_path / "pairs.txt").write_text("a.png ghost.png\n")
        argv = ["match", str(feats), str(tmp_path / "pairs.txt"), str(out)]
        expected = "ghost.png"
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        features_main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("error: ") and expected in err and "Traceback" not in err
    assert not out.exists() and not list(out.parent.glob(".out.*"))


# ------------------------------------------------------------------------------------------------- torch module


@pytest.fixture(scope="module")
def uwnet():
    from ruslam.models.uwnet_module import UWNetFeatures

    return UWNetFeatures(max_keypoints=300, min_pixels=None)  # the images' own size (multiples of 8): fast


def test_module_matches_the_extractor_and_is_differentiable(uwnet):
    image = textured()
    ref = load_extractor("uwnet_xfeat", max_keypoints=300, min_pixels=None).extract(image)
    x = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255
    x = torch.cat([x, x.flip(-1)])
    uwnet.zero_grad()
    feats = uwnet(x)
    assert len(feats) == 2
    assert np.allclose(feats[0]["keypoints"].detach().numpy(), ref["keypoints"], atol=1e-3)
    assert np.allclose(feats[0]["descriptors"].detach().numpy(), ref["descriptors"], atol=1e-4)
    (feats[0]["descriptors"].sum() + feats[1]["keypoints"].sum()).backward()  # descriptors and sub-pixel offsets
    grads = [p.grad for p in uwnet.parameters() if p.grad is not None]
    assert grads and sum(float(g.abs().sum()) for g in grads) > 0
    lg = uwnet.extract(x)
    n = lg["keypoints"].shape[1]
    assert lg["keypoints"].shape == (2, n, 2) and lg["descriptors"].shape == (2, n, 64)
    assert lg["keypoint_scores"].shape == (2, n) and lg["image_size"].tolist() == [[320, 240], [320, 240]]
    assert n == min(len(f["keypoints"]) for f in feats)


def test_onnx_export_decodes_to_the_module_output(uwnet, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    from ruslam.models.uwnet_module import decode_onnx, export_onnx

    uwnet_native = uwnet
    path = export_onnx(uwnet_native, tmp_path / "uwnet.onnx", height=88, width=120)  # not multiples of 32
    x = torch.from_numpy(textured(88, 120)).permute(2, 0, 1)[None].float() / 255
    session = ort.InferenceSession(str(path))
    outputs = dict(zip([o.name for o in session.get_outputs()], session.run(None, {"image": x.numpy()}), strict=True))
    assert set(outputs) == {"keypoint_logits", "dense_descriptors", "global_descriptor", "reliability"}
    got = decode_onnx(outputs, conf={"max_keypoints": 300})[0]
    with torch.no_grad():
        want = uwnet_native(x)[0]
        dense = uwnet_native.dense(x)
    for name, value in dense.items():
        if name == "global_descriptor":
            assert_same_global_descriptor(outputs[name], value.numpy())
        else:
            assert np.abs(outputs[name] - value.numpy()).max() < 1e-4, name
    n = min(len(got["keypoints"]), len(want["keypoints"]))
    assert n > 20 and abs(len(got["keypoints"]) - len(want["keypoints"])) <= 2
    close = np.linalg.norm(got["keypoints"][:, None] - want["keypoints"].numpy()[None], axis=-1).min(1) < 0.05
    assert close.mean() > 0.95


# ------------------------------------------------------------------------------------------ docs/pipelines.md


@pytest.mark.slow
def test_docs_pipelines_examples_run(tmp_path, monkeypatch, capsys):
    """Every ```python block of docs/pipelines.md, in order, in one namespace, in a folder holding images/."""
    from ruslam.data.multiview import MultiViewConfig, render_multiview

    src = render_multiview(MultiViewConfig(num_views=4, width=320, height=240, focal=225.0), cache_dir=tmp_path)
    (tmp_path / "work" / "images").mkdir(parents=True)
    for p in sorted(src.glob("*.png")):
        (tmp_path / "work" / "images" / p.name).write_bytes(p.read_bytes())
    monkeypatch.chdir(tmp_path / "work")
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "pipelines.md").read_text(), re.S)
    assert len(blocks) == 5
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, "docs/pipelines.md", "exec"), namespace)  # noqa: S102
    out = capsys.readouterr().out
    assert "pairs;" in out and "matches" in out
