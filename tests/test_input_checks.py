"""Every registered extractor refuses bad images with the same InputError (one shared `check_image`), and files
written through `ruslam.atomic_files` appear whole or not at all."""

from __future__ import annotations

import numpy as np
import pytest

from ruslam import load_extractor
from ruslam.atomic_files import atomic_path, atomic_write
from ruslam.errors import InputError, MissingWeights
from ruslam.models.registry import EXTRACTORS

BAD_IMAGES = {
    "NaN": (np.full((64, 64, 3), np.nan, np.float32), "NaN or infinite"),
    "inf": (np.full((64, 64), np.inf, np.float64), "NaN or infinite"),
    "0-255 float": (np.full((64, 64, 3), 200.0, np.float32), r"must lie in \[0, 1\]"),
    "negative float": (np.full((64, 64), -0.5, np.float32), r"must lie in \[0, 1\]"),
    "4 channels": (np.zeros((64, 64, 4), np.uint8), "HxW or HxWx3"),
    "int32": (np.zeros((64, 64), np.int32), "uint8 or float"),
    "tiny": (np.zeros((8, 8), np.uint8), "at least 16x16"),
    "list": ([[0] * 64] * 64, "numpy array"),
}


@pytest.fixture(scope="module", params=sorted(EXTRACTORS))
def extractor(request):
    if request.param == "superpoint":  # its weights cannot be downloaded here; random ones check the input the same
        from ruslam.models.pretrained.superpoint import SuperPoint, SuperPointNet

        return SuperPoint(net=SuperPointNet())
    try:
        return load_extractor(request.param)
    except MissingWeights as err:  # an extractor whose weights are absent on this machine
        pytest.skip(str(err))


@pytest.mark.parametrize("case", sorted(BAD_IMAGES))
def test_every_extractor_refuses_bad_images_the_same_way(extractor, case):
    image, message = BAD_IMAGES[case]
    with pytest.raises(InputError, match=message):
        extractor.extract(image)


def test_every_extractor_accepts_grey_uint8_and_float_at_the_range_ends(extractor):
    rng = np.random.default_rng(0)
    for image in (rng.integers(0, 256, (64, 80), np.uint8), rng.random((64, 80, 3)).astype(np.float32),
                  np.clip(rng.random((64, 80, 1)) * 1.0005, 0, 1.0005)):
        out = extractor.extract(image)
        assert out["keypoints"].shape[1] == 2 and len(out["keypoints"]) == len(out["descriptors"])


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    path = atomic_write(tmp_path / "sub" / "table.md", "old\n")
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half of the new ta")
        raise RuntimeError("crash mid-write")
    assert path.read_text() == "old\n" and sorted(p.name for p in path.parent.iterdir()) == ["table.md"]
    atomic_write(path, b"new\n")
    assert path.read_bytes() == b"new\n" and sorted(p.name for p in path.parent.iterdir()) == ["table.md"]


def test_the_temporary_name_keeps_the_suffix_that_picks_the_format(tmp_path):
    with atomic_path(tmp_path / "plot.png") as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path and tmp.name.startswith(".")
        tmp.write_bytes(b"x")
    assert (tmp_path / "plot.png").read_bytes() == b"x"
