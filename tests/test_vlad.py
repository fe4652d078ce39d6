from pathlib import Path

import numpy as np
import pytest
import torch

from ruslam.models.pretrained.vlad import VLAD, fit_codebook, save_codebook, vlad_aggregate

ROOT = Path(__file__).resolve().parents[1]


def reference_vlad(dense: np.ndarray, codebook: np.ndarray, power=0.5) -> np.ndarray:
    """Plain loops from the VLAD definition, for one image [D, h, w]."""
    x = dense.reshape(dense.shape[0], -1).T
    blocks = np.zeros_like(codebook)
    for v in x:
        k = np.argmin(((codebook - v) ** 2).sum(1))
        blocks[k] += v - codebook[k]
    for k in range(len(blocks)):
        n = np.linalg.norm(blocks[k])
        blocks[k] = blocks[k] / n if n > 0 else 0
    out = np.sign(blocks) * np.abs(blocks) ** power
    out = out.ravel()
    return out / np.linalg.norm(out)


def test_aggregation_matches_the_definition():
    rng = np.random.default_rng(0)
    dense = rng.normal(size=(2, 6, 5, 7)).astype(np.float32)
    codebook = rng.normal(size=(5, 6)).astype(np.float32)
    codebook[4] = 100.0  # a centre no descriptor is assigned to: its block stays zero
    out = vlad_aggregate(torch.from_numpy(dense), torch.from_numpy(codebook)).numpy()
    assert out.shape == (2, 30)
    for i in range(2):
        np.testing.assert_allclose(out[i], reference_vlad(dense[i], codebook), atol=1e-5)
    assert np.all(out[:, 24:] == 0)


def test_kmeans_is_seeded_and_finds_separated_centres():
    rng = np.random.default_rng(1)
    true = rng.normal(size=(4, 3)) * 10
    data = np.concatenate([c + 0.1 * rng.normal(size=(50, 3)) for c in true])
    a, b = fit_codebook(data, 4, seed=3), fit_codebook(data, 4, seed=3)
    np.testing.assert_array_equal(a, b)
    assert a.dtype == np.float32 and a.shape == (4, 3)
    nearest = np.sqrt(((a[:, None] - true[None]) ** 2).sum(-1)).min(1)
    assert np.all(nearest < 0.1)
    with pytest.raises(ValueError, match="at least 64 descriptors"):
        fit_codebook(data[:10], 64)


def test_codebook_files_are_validated(tmp_path):
    good = np.random.default_rng(0).normal(size=(4, 8)).astype(np.float32)
    save_codebook(good, tmp_path / "cb.npy")
    head = VLAD(num_clusters=4, dim=8, codebook=str(tmp_path / "cb.npy"))
    assert head.fitted and torch.equal(head.codebook, torch.from_numpy(good))
    with pytest.raises(ValueError, match=r"has shape \(4, 8\), expected finite \(64, 64\)"):
        VLAD(codebook=str(tmp_path / "cb.npy"))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        VLAD(codebook=str(tmp_path / "nope.npy"))
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    with pytest.raises(ValueError, match="not a readable .npy array"):
        VLAD(num_clusters=4, dim=8, codebook=str(tmp_path / "junk.npy"))
    with pytest.raises(RuntimeError, match="codebook is not fitted"):
        VLAD(num_clusters=4, dim=8)(None, {"dense_descriptors": torch.rand(1, 8, 2, 2)})


def test_teacher_configs_build_the_three_cache_targets(tmp_path):
    from hydra.utils import get_class, instantiate
    from omegaconf import OmegaConf

    conf = OmegaConf.load(ROOT / "conf/teacher/xfeat_vlad.yaml")
    codebook = np.random.default_rng(0).normal(size=(64, 64)).astype(np.float32)
    save_codebook(codebook, tmp_path / "cb.npy")
    conf.global_head.codebook = str(tmp_path / "cb.npy")
    teacher = instantiate(conf)
    out = teacher(torch.rand(1, 3, 64, 96))
    assert out["keypoint_logits"].shape == (1, 65, 8, 12) and out["dense_descriptors"].shape == (1, 64, 8, 12)
    assert out["global_descriptor"].shape == (1, 4096)
    torch.testing.assert_close(out["global_descriptor"].norm(dim=1), torch.ones(1))
    paper = OmegaConf.load(ROOT / "conf/teacher/superpoint_netvlad.yaml")
    assert OmegaConf.is_missing(paper.global_head, "weights")  # user-supplied NetVLAD weights are mandatory
    for target in [paper._target_, paper.local._target_, paper.global_head._target_]:
        assert get_class(target)


def test_packaged_vlad_retrieves_its_scene_across_water_types():
    """Must reach: 20 procedural scenes; database views under clear oceanic water (IB), queries from a jittered
    camera (5 deg, 0.2 m) under turbid coastal water (3C); each query's best match is its own scene (recall@1)."""
    from ruslam import load_extractor
    from ruslam.data.procedural import ProceduralRGBD
    from ruslam.data.synthesis import PseudoUnderwater

    scenes = ProceduralRGBD(20, height=192, width=256, seed=77)  # not the seed the packaged codebook was fitted on
    xfeat = load_extractor("xfeat", max_keypoints=1)
    synthesis = PseudoUnderwater(noise_std=0.01, low_light=1.0, seed=0)

    def global_descriptor(view, water, index):
        rgb, depth = torch.from_numpy(view["image"]).permute(2, 0, 1)[None], torch.from_numpy(view["depth"])[None]
        degraded = synthesis.for_water_type(water)(rgb, depth, [index])[0].permute(1, 2, 0).numpy()
        return xfeat.extract(degraded)["global_descriptor"]

    database = np.stack([global_descriptor(scenes.render_view(i), "IB", i) for i in range(20)])
    queries = np.stack([
        global_descriptor(scenes.render_view(i, camera_jitter=(5.0, 0.2), jitter_seed=1), "3C", 100 + i)
        for i in range(20)
    ])
    recall_at_1 = np.mean((queries @ database.T).argmax(axis=1) == np.arange(20))
    assert recall_at_1 >= 0.9
