"""The shipped UWNet checkpoint has learned something: on a fixed turbid, rotated pair it matches where the same
architecture with random weights does not (a shape check on a grey image passes with random weights too)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ruslam import load_extractor
from ruslam.data.procedural import ProceduralRGBD
from ruslam.data.synthesis import PseudoUnderwater
from ruslam.data.upatches import sample_homography, warp_image
from ruslam.eval.matching import evaluate_pair
from ruslam.models.export import build_network, export_weights


@pytest.fixture(scope="module")
def turbid_rotated_pair():
    """Procedural scene 3 in Jerlov 3C water (eq. 4), and its view rotated by -12.4 degrees (seeded homography)."""
    sample = ProceduralRGBD(num_images=4, height=240, width=320, seed=0)[3]
    depth = np.where(np.isfinite(sample["depth"]), sample["depth"], np.inf)
    water = PseudoUnderwater(seed=0).for_water_type("3C")
    uw = water(torch.from_numpy(sample["image"]).permute(2, 0, 1)[None], torch.from_numpy(depth)[None], [3])
    image1 = np.round(uw[0].permute(1, 2, 0).clamp(0, 1).numpy() * 255).astype(np.uint8)
    H, angle = sample_homography(np.random.default_rng(3), image1.shape[:2], 15.0, (0.8, 0.9), 0.05)
    assert 10 < abs(angle) < 15
    return image1, warp_image(image1, H), H


def _mma3(extractor, pair) -> float:
    image1, image2, H = pair
    result = evaluate_pair(extractor.extract(image1), extractor.extract(image2), H, image1.shape[:2],
                           image2.shape[:2], binary=False)
    return float(result.mma[2])  # thresholds 1..10 px: index 2 is 3 px


def test_shipped_checkpoint_beats_its_untrained_network(turbid_rotated_pair, tmp_path):
    shipped = load_extractor("uwnet_xfeat")
    torch.manual_seed(0)
    untrained = load_extractor(export_weights(build_network(shipped.net.config), tmp_path / "untrained.pt"))
    trained_mma, untrained_mma = _mma3(shipped, turbid_rotated_pair), _mma3(untrained, turbid_rotated_pair)
    assert trained_mma >= untrained_mma + 0.05, (trained_mma, untrained_mma)
