"""NYU-Depth-v2 labeled set (``nyu_depth_v2_labeled.mat``, 1,449 RGB-D images) with the paper's split.

The file is MATLAB v7.3, i.e. HDF5, read with h5py.  MATLAB writes arrays column-major, so h5py sees them with
their axes reversed: ``images`` is (N, 3, W, H) uint8 and ``depths`` (N, W, H) float metres (the in-painted,
hole-filled depth of the labeled set).  `NYUDepthV2` undoes the transposition to HxWx3 / HxW.

Split (paper, section 4.1): 200 images drawn at random as the test set, the other 1,249 for training; drawn
here with ``np.random.default_rng(split_seed).permutation(N)[:num_test]`` so the split is reproducible.

The HDF5 file is opened lazily, once per process (DataLoader workers each open their own handle; the dataset
pickles without one).  Sample ids are ``nyu-0042``: the 0-based index in the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from ruslam.data.rgbd_sample import make_sample
from ruslam.errors import InputError, MissingInput

SPLITS = ("train", "test", "all")
NYU_LABELED_URL = "http://horatio.cs.nyu.edu/mit/silberman/nyu_depth_v2/nyu_depth_v2_labeled.mat"


def split_indices(num_images: int, split: str, num_test: int = 200, split_seed: int = 0) -> np.ndarray:
    """Sorted file indices of ``split``: test = ``num_test`` seeded random images, train = the rest."""
    if split not in SPLITS:
        raise InputError(f"Unknown NYU split {split!r}; expected one of {SPLITS}.")
    if not 0 < num_test < num_images:
        raise InputError(f"num_test must be between 1 and {num_images - 1} (the file has {num_images} images), "
                         f"got {num_test}.")
    if split == "all":
        return np.arange(num_images)
    perm = np.random.default_rng(split_seed).permutation(num_images)
    return np.sort(perm[:num_test] if split == "test" else perm[num_test:])


class NYUDepthV2:
    """Map-style RGB-D dataset over the labeled ``.mat``; ``ds[i]`` -> ``{"id", "image", "depth"}``."""

    def __init__(self, path: str | Path, split: str = "test", num_test: int = 200, split_seed: int = 0):
        self.path = Path(path)
        num_images = self._check_file(self.path)
        self.split = split
        self.indices = split_indices(num_images, split, num_test, split_seed)
        self._file: h5py.File | None = None
        self._pid: int | None = None

    @staticmethod
    def _check_file(path: Path) -> int:
        if not path.is_file():
            raise MissingInput(f"NYU-Depth-v2 file {path} does not exist; download {NYU_LABELED_URL} "
                                    f"(2.8 GB) and pass its path.")
        if not h5py.is_hdf5(path):
            raise InputError(f"{path} is not an HDF5 file; expected the MATLAB v7.3 nyu_depth_v2_labeled.mat.")
        with h5py.File(path, "r") as f:
            for key in ("images", "depths"):
                if not isinstance(f.get(key), h5py.Dataset):
                    raise InputError(f"{path} has no dataset {key!r}; expected the NYU-Depth-v2 labeled .mat "
                                     f"with 'images' (N,3,W,H) and 'depths' (N,W,H).")
            images, depths = f["images"].shape, f["depths"].shape
        if len(images) != 4 or images[1] != 3 or len(depths) != 3:
            raise InputError(f"{path}: 'images' must be (N,3,W,H) and 'depths' (N,W,H), got {images} and {depths}.")
        if images[0] != depths[0] or images[2:] != depths[1:]:
            raise InputError(f"{path}: 'images' {images} and 'depths' {depths} differ in image count or size; "
                             f"each RGB image needs a depth map of the same size.")
        return images[0]

    def _handle(self) -> h5py.File:
        if self._file is None or self._pid != os.getpid():  # a forked worker must not reuse the parent's handle
            self._file, self._pid = h5py.File(self.path, "r"), os.getpid()
        return self._file

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_file": None, "_pid": None}

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> dict:
        if not -len(self) <= i < len(self):
            raise IndexError(f"NYU {self.split} index {i} is out of range for {len(self)} images.")
        index = int(self.indices[i])
        f = self._handle()
        image = np.ascontiguousarray(f["images"][index].transpose(2, 1, 0))  # (3,W,H) -> (H,W,3)
        depth = np.ascontiguousarray(f["depths"][index].T)  # (W,H) -> (H,W)
        return make_sample(f"nyu-{index:04d}", image, depth, source=str(self.path))
