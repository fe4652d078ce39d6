import numpy as np
import pytest
import torch

from ruslam.data.procedural import ProceduralRGBD
from ruslam.errors import InputError
from ruslam.models.lightglue import LightGlueMatcher
from ruslam.models.registry import load_extractor


@pytest.fixture(scope="module")
def xfeat_matcher():
    return LightGlueMatcher("xfeat")


@pytest.fixture(scope="module")
def shifted_pair():
    """A textured scene and a crop of it moved by (17, 9) px: image 2 pixel = image 1 pixel - shift."""
    scene = (ProceduralRGBD(num_images=1, height=300, width=380, seed=3)[0]["image"] * 255).astype(np.uint8)
    shift = np.array([17, 9])
    return scene[:240, :320], scene[9:249, 17:337], shift


def test_lighterglue_matches_xfeat_keypoints_by_a_known_shift(xfeat_matcher, shifted_pair):
    a, b, shift = shifted_pair
    ex = load_extractor("xfeat", max_keypoints=600)
    fa, fb = ex.extract(a), ex.extract(b)
    i0, i1 = xfeat_matcher(fa["keypoints"], fa["descriptors"], (320, 240), fb["keypoints"], fb["descriptors"],
                           (320, 240))
    assert len(i0) == len(i1) and len(np.unique(i0)) == len(i0) and len(np.unique(i1)) == len(i1)  # one-to-one
    err = np.linalg.norm(fa["keypoints"][i0] - shift - fb["keypoints"][i1], axis=1)
    assert len(i0) >= 100
    assert np.mean(err < 4.0) >= 0.9  # XFeat re-detects to within a few px after a shift (keypoint_shift bench)


def test_random_descriptors_give_few_matches(xfeat_matcher):
    """LightGlue's confidence filter must reject pairs that do not look alike: no match 'by position' alone."""
    rng = np.random.default_rng(0)
    kp = rng.uniform(0, 300, (300, 2))
    d0, d1 = (torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(300, 64))).float(), dim=1).numpy()
              for _ in range(2))
    i0, _ = xfeat_matcher(kp, d0, (320, 320), kp, d1, (320, 320))
    same, _ = xfeat_matcher(kp, d0, (320, 320), kp, d0, (320, 320))
    assert len(i0) < 30 and len(same) > 250


def test_degenerate_input_and_bad_names():
    m = LightGlueMatcher.__new__(LightGlueMatcher)  # no weights needed for the empty case
    i0, i1 = LightGlueMatcher.__call__(m, np.zeros((1, 2)), np.zeros((1, 64)), (8, 8), np.zeros((5, 2)),
                                       np.zeros((5, 64)), (8, 8))
    assert len(i0) == len(i1) == 0
    with pytest.raises(ValueError, match="No LightGlue weights for 'orb'"):
        LightGlueMatcher("orb")
    with pytest.raises(ValueError, match="filter_threshold"):
        LightGlueMatcher("xfeat", filter_threshold=1.5)


def test_weights_of_another_matcher_are_one_sentence(tmp_path):
    """XFeat's LighterGlue (64 -> 96 dims, 6 layers) cannot load a state dict of another shape."""
    bad = tmp_path / "other.pt"
    torch.save({"input_proj.weight": torch.zeros(3, 3)}, bad)
    with pytest.raises(InputError, match="does not match LightGlue"):
        LightGlueMatcher("xfeat", weights=bad)
