import numpy as np
import pytest
import torch

from ruslam import load_extractor
from ruslam.models.extractor import (
    cell_logits_to_heatmap,
    detect_keypoints,
    refine_subpixel,
    sample_dense,
    simple_nms,
)


def test_sampling_convention_hits_cell_centres():
    s, h, w = 8, 4, 5
    ys, xs = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    dense = torch.stack([xs, ys])[None]  # channel 0 = cell column, channel 1 = cell row
    # pixel centre of cell (i, j) is j*s + (s-1)/2; halfway between two cells is j*s + s - 0.5
    kp = torch.tensor([[[2 * s + 3.5, 1 * s + 3.5], [0 * s + 3.5, 3 * s + 3.5], [1 * s + 7.5, 2 * s + 3.5]]])
    out = sample_dense(dense, kp, s)[0]
    assert torch.allclose(out, torch.tensor([[2.0, 1.0], [0.0, 3.0], [1.5, 2.0]]), atol=1e-5)


def test_nms_keeps_only_local_maxima():
    heat = torch.zeros(1, 9, 9)
    heat[0, 4, 4], heat[0, 4, 5], heat[0, 0, 0] = 1.0, 0.9, 0.5
    kept = simple_nms(heat, 1)
    assert kept[0, 4, 4] == 1.0 and kept[0, 4, 5] == 0 and kept[0, 0, 0] == 0.5


def test_cell_layout_puts_each_channel_at_its_pixel():
    logits = torch.full((1, 65, 2, 3), -20.0)
    logits[0, 8 * 2 + 5, 1, 2] = 20.0  # cell (1, 2), row 2 col 5 inside the cell
    logits[0, 64] = 20.0
    logits[0, 64, 1, 2] = -20.0
    heat = cell_logits_to_heatmap(logits)
    assert heat.shape == (1, 16, 24)
    kps = detect_keypoints(heat, nms_radius=4, threshold=0.5, max_keypoints=10, border=0)
    xy, _ = kps[0]
    assert xy.tolist() == [[2 * 8 + 5, 1 * 8 + 2]]


def test_border_and_topk():
    heat = torch.rand(1, 40, 40, generator=torch.Generator().manual_seed(0))
    (xy, scores), = detect_keypoints(heat.clone(), nms_radius=0, threshold=0.0, max_keypoints=7, border=4)
    assert len(xy) == 7 and (xy >= 4).all() and (xy < 36).all()
    assert torch.all(scores[:-1] >= scores[1:])


@pytest.mark.parametrize("name", ["orb", "sift"])
def test_classical_extractors_follow_the_contract(name):
    rng = np.random.default_rng(0)
    img = (rng.random((120, 160)) * 255).astype(np.uint8)
    img = np.kron(img[::4, ::4], np.ones((4, 4), np.uint8))  # blocky texture with corners
    out = load_extractor(name, max_keypoints=100).extract(np.dstack([img] * 3))
    n = len(out["keypoints"])
    assert 0 < n <= 100
    assert out["keypoints"].shape == (n, 2) and out["scores"].shape == (n,) and len(out["descriptors"]) == n
    assert (out["keypoints"] >= 0).all() and (out["keypoints"][:, 0] < 160).all()
    if name == "orb":  # the pyramid level each keypoint was found on, as its scale
        levels = np.log(out["scales"]) / np.log(1.2)
        assert out["scales"].shape == (n,) and np.allclose(levels, np.round(levels), atol=1e-4)
        assert len(set(np.round(levels))) > 1 and levels.min() > -0.5 and levels.max() < 7.5


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="Unknown extractor 'nope'"):
        load_extractor("nope")
    with pytest.raises(ValueError, match="uint8 or float"):
        load_extractor("orb").extract(np.zeros((32, 32), np.int32))
    with pytest.raises(ValueError, match="HxW or HxWx3"):
        load_extractor("orb").extract(np.zeros((32, 32, 4), np.uint8))
    with pytest.raises(ValueError, match="unknown option"):
        load_extractor("orb", nfeatures=3)


def test_separable_nms_equals_the_square_window_max():
    scores = torch.rand(2, 37, 53, generator=torch.Generator().manual_seed(1))
    scores[0, 10:14, 20:24] = 0.999  # plateaus keep every tied maximum, as the square window does
    for radius in (1, 2, 4):
        square = torch.nn.functional.max_pool2d(scores[:, None], 2 * radius + 1, stride=1, padding=radius)[:, 0]
        expected = torch.where(scores == square, scores, torch.zeros_like(scores))
        assert torch.equal(simple_nms(scores, radius), expected)


def test_subpixel_refinement_finds_the_centre_of_a_blob_between_pixels():
    ys, xs = torch.meshgrid(torch.arange(32.0), torch.arange(40.0), indexing="ij")
    centres = torch.tensor([[10.3, 7.6], [25.7, 20.2]])  # (x, y)
    heat = sum(torch.exp(-((xs - x) ** 2 + (ys - y) ** 2) / 2.0) for x, y in centres)
    (xy, _), = detect_keypoints(heat[None].clone(), 2, 0.1, 0, 0)
    xy = xy[xy[:, 0].argsort()]
    assert torch.equal(xy, centres.round())  # the detector alone is off by up to half a pixel
    refined = refine_subpixel(heat, xy, 3)
    assert torch.allclose(refined, centres, atol=0.05)
    assert torch.equal(refine_subpixel(heat, xy[:0], 3), xy[:0])
