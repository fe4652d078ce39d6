"""ALIKED-n16rot as the keypoint teacher, XFeat as the descriptor teacher (`teacher=aliked_xfeat_vlad`).

Why: on the procedural Upatches, ALIKED's keypoints with XFeat's descriptors sampled at them score MMA@3 86.3 at
0-30° against XFeat's own 63.6, and XFeat's keypoints with ALIKED's descriptors 60.4 (BENCHMARKS.md,
`bench/part_swap.py`): the student's detector, not its descriptor, is what separates it from ALIKED.

ALIKED's dense score map (sigmoid, full resolution) is pooled into the 65-cell layout of the student's keypoint
head: in each 8x8 cell, the pixels that are local maxima of the score map (ALIKED's own NMS radius) carry their
score, the dustbin carries one minus the cell's best score, and the target is that distribution (returned as its
log, so that `DistillationLoss`'s softmax gives it back). A cell with one keypoint of score s thus puts s on it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ruslam.models.extractor import simple_nms
from ruslam.models.pretrained.xfeat import STRIDE, XFeatTeacher

EPS = 1e-6


def pool_score_map(score: torch.Tensor, nms_radius: int = 2) -> torch.Tensor:
    """Score map [B, 1, H, W] in [0, 1] (H, W multiples of 8) -> log target distribution [B, 65, H/8, W/8]."""
    peaks = simple_nms(score[:, 0], nms_radius)[:, None]  # non-maxima zeroed
    cells = F.pixel_unshuffle(peaks, STRIDE)  # [B, 64, h, w], channel 8*row + col as the keypoint head
    dustbin = 1.0 - cells.amax(dim=1, keepdim=True)
    dist = torch.cat([cells, dustbin], dim=1)
    dist = dist / dist.sum(dim=1, keepdim=True).clamp_min(EPS)
    return dist.clamp_min(EPS).log()


class ALIKEDKeypointTeacher(nn.Module):
    """image [B, 3, H, W] in [0, 1] -> ``keypoint_logits`` from ALIKED's score map, ``dense_descriptors`` from
    XFeat (so the student's descriptor and global targets stay those of `xfeat_vlad`)."""

    descriptor_dim = XFeatTeacher.descriptor_dim

    def __init__(self, model: str = "aliked-n16rot", nms_radius: int = 2, weights: str | None = None):
        super().__init__()
        from ruslam.models.pretrained.aliked_disk import ALIKED  # noqa: PLC0415 (optional package: one sentence when it is missing)

        self.aliked = ALIKED(model=model).net  # only its dense score map is used
        self.xfeat = XFeatTeacher(weights)  # `weights`: XFeat's, as in `xfeat_vlad`
        self.nms_radius = nms_radius

    def train(self, mode: bool = True):  # frozen teacher
        return super().train(False)

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        _, score = self.aliked.extract_dense_map(image.float())
        out = self.xfeat(image)
        out["keypoint_logits"] = pool_score_map(score, self.nms_radius)
        return out
