"""NYU-Depth-v2 labeled .mat reader on a tiny fake v7.3-like HDF5 file with the real dataset names and layout."""

from __future__ import annotations

import pickle
from pathlib import Path

import h5py
import numpy as np
import pytest

from ruslam.data.nyu import NYUDepthV2, split_indices

N, H, W = 12, 4, 6  # asymmetric H != W so a wrong transposition cannot pass


def _write(path: Path, images: np.ndarray | None = None, depths: np.ndarray | None = None) -> Path:
    with h5py.File(path, "w") as f:
        if images is not None:
            f["images"] = images
        if depths is not None:
            f["depths"] = depths
    return path


@pytest.fixture
def nyu_file(tmp_path) -> Path:
    """As MATLAB v7.3 stores it: images (N, 3, W, H) uint8, depths (N, W, H) metres."""
    images = np.zeros((N, 3, W, H), np.uint8)
    depths = np.full((N, W, H), 3.0, np.float32)
    for n in range(N):
        images[n, 0, 5, 1] = 255  # pixel at row 1, column 5 is pure red
        images[n, 2, 0, 3] = 51  # pixel at row 3, column 0 has blue 0.2
        depths[n, 5, 1] = 1.0 + n  # image n carries its index in the depth at row 1, column 5
        depths[n, 2, 2] = 0.0  # an invalid (hole) pixel at row 2, column 2
    return _write(tmp_path / "nyu_depth_v2_labeled.mat", images, depths)


def test_transposition_is_undone(nyu_file):
    ds = NYUDepthV2(nyu_file, split="all", num_test=3)
    s = ds[7]
    assert s["id"] == "nyu-0007"
    assert s["image"].shape == (H, W, 3) and s["image"].dtype == np.float32
    assert s["depth"].shape == (H, W) and s["depth"].dtype == np.float32
    np.testing.assert_array_equal(s["image"][1, 5], [1.0, 0.0, 0.0])
    assert s["image"][3, 0, 2] == pytest.approx(0.2)
    assert s["image"].sum() == pytest.approx(1.2)  # nothing else lit
    assert s["depth"][1, 5] == pytest.approx(8.0)
    assert np.isnan(s["depth"][2, 2]) and np.isnan(s["depth"]).sum() == 1
    assert s["depth"][0, 0] == pytest.approx(3.0)


def test_split_is_seeded_disjoint_and_complete(nyu_file):
    test = NYUDepthV2(nyu_file, split="test", num_test=3, split_seed=1)
    train = NYUDepthV2(nyu_file, split="train", num_test=3, split_seed=1)
    assert len(test) == 3 and len(train) == N - 3
    assert set(test.indices).isdisjoint(train.indices)
    assert sorted([*test.indices, *train.indices]) == list(range(N))
    np.testing.assert_array_equal(test.indices, NYUDepthV2(nyu_file, "test", num_test=3, split_seed=1).indices)
    # the sample of a test index really is that image of the file
    assert test[0]["depth"][1, 5] == pytest.approx(1.0 + test.indices[0])


def test_paper_split_sizes_and_seed_dependence():
    test, train = split_indices(1449, "test"), split_indices(1449, "train")
    assert len(test) == 200 and len(train) == 1249 and len(np.union1d(test, train)) == 1449
    assert not np.array_equal(test, split_indices(1449, "test", split_seed=1))


def test_dataset_pickles_without_an_open_handle(nyu_file):
    ds = NYUDepthV2(nyu_file, split="test", num_test=3)
    ds[0]  # opens the file
    clone = pickle.loads(pickle.dumps(ds))
    np.testing.assert_array_equal(clone[1]["image"], ds[1]["image"])


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        NYUDepthV2(tmp_path / "nope.mat")


def test_non_hdf5_file(tmp_path):
    path = tmp_path / "old.mat"
    path.write_bytes(b"MATLAB 5.0 MAT-file" + bytes(200))
    with pytest.raises(ValueError, match="not an HDF5 file"):
        NYUDepthV2(path)


def test_missing_key(tmp_path):
    path = _write(tmp_path / "x.mat", images=np.zeros((N, 3, W, H), np.uint8))
    with pytest.raises(ValueError, match="no dataset 'depths'"):
        NYUDepthV2(path)


def test_rgb_depth_size_mismatch(tmp_path):
    path = _write(tmp_path / "x.mat", np.zeros((N, 3, W, H), np.uint8), np.ones((N, W, H + 1), np.float32))
    with pytest.raises(ValueError, match="differ in image count or size"):
        NYUDepthV2(path)


def test_all_invalid_depth_names_the_image(tmp_path):
    depths = np.ones((N, W, H), np.float32)
    depths[4] = np.nan
    depths[4, 0, 0] = -1.0
    depths[4, 1, 0] = np.inf
    path = _write(tmp_path / "x.mat", np.zeros((N, 3, W, H), np.uint8), depths)
    ds = NYUDepthV2(path, split="all", num_test=3)
    with pytest.raises(ValueError, match="'nyu-0004'.*no valid pixel"):
        ds[4]


def test_bad_split_name(nyu_file):
    with pytest.raises(ValueError, match="Unknown NYU split"):
        NYUDepthV2(nyu_file, split="val")


def test_hydra_config_builds_the_train_split(nyu_file):
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "data" / "nyu.yaml")
    ds = instantiate(cfg, path=str(nyu_file), num_test=3)
    assert isinstance(ds, NYUDepthV2) and ds.split == "train" and len(ds) == N - 3
