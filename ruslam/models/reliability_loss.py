"""Reliability loss: XFeat's reliability map taught which cells match, under the student's water and rotation.

XFeat ranks its keypoints by keypoint score x reliability, where the reliability head (a per-cell map on the
backbone features) was trained to predict whether a cell's descriptor finds its true correspondence. The student
keeps that head untrained while its backbone is fine-tuned on pseudo-underwater views, so the ranking no longer
describes the student's descriptors in turbid water. This loss re-teaches it the way XFeat did: for the cells of
view A sampled by the correspondence loss, the target is 1 when the cell's nearest neighbour among view B's
descriptors at the sampled correspondences is its own, else 0 (binary cross-entropy). The targets come from
detached descriptors and the student feeds the head detached features, so only the head learns from this term.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ReliabilityLoss(nn.Module):
    def forward(self, reliability_a: torch.Tensor, samples: list) -> torch.Tensor:
        """reliability_a [B, 1, h, w] in (0, 1) for view A; samples from `CorrespondenceLoss.sample`.
        Returns the mean BCE over every sampled cell (0 if there is none)."""
        probs, targets = [], []
        for i, idx, cos in samples:
            cos = cos.detach()
            targets.append((cos.argmax(1) == torch.arange(len(idx), device=cos.device)).to(reliability_a.dtype))
            probs.append(reliability_a[i].flatten()[idx])
        if not probs:
            return reliability_a.sum() * 0.0
        p = torch.cat(probs).clamp(1e-6, 1 - 1e-6)
        return F.binary_cross_entropy(p, torch.cat(targets))
