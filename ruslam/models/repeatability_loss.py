"""Repeatability loss: the student's keypoint heat of two warped views of one image made to agree (after R2D2).

The detector is distilled view by view from the teacher's map; where the student cannot copy it (its cell head
stays far from ALIKED's map, README), its misses differ from view to view, and a keypoint that moves between
views is a wrong match at 3 px. This term compares the views directly: view B's full-resolution heat is warped
into view A by the known homography, and in every valid `patch` x `patch` window the two are asked to have cosine
similarity 1 (R2D2, Revaud et al. 2019), each window's mean removed first (a correlation): with plain cosines a
flat heat agrees with itself everywhere, and training on them flattened the student's peaks (BENCHMARKS.md). Both
views receive the gradient.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ruslam.models.extractor import cell_logits_to_heatmap


class RepeatabilityLoss(nn.Module):
    def __init__(self, patch: int = 16, min_valid: float = 0.9):
        super().__init__()
        if patch < 2 or not 0 < min_valid <= 1:
            raise ValueError(f"RepeatabilityLoss needs patch >= 2 and 0 < min_valid <= 1, got {patch}, {min_valid}.")
        self.patch, self.min_valid = patch, min_valid

    def forward(self, logits_a: torch.Tensor, logits_b: torch.Tensor, homography_ab: torch.Tensor,
                mask_a: torch.Tensor | None = None) -> torch.Tensor:
        """logits_a, logits_b [B, 65, h, w] cell logits; homography_ab [B, 3, 3] maps view-A pixels to view-B
        pixels; mask_a [B, h, w] valid cells of A. Returns 1 - the mean correlation over windows at least
        `min_valid` inside both views (0 if there is none)."""
        heat_a, heat_b = cell_logits_to_heatmap(logits_a), cell_logits_to_heatmap(logits_b)
        b, H, W = heat_a.shape
        ys, xs = torch.meshgrid(torch.arange(H, device=heat_a.device, dtype=heat_a.dtype),
                                torch.arange(W, device=heat_a.device, dtype=heat_a.dtype), indexing="ij")
        pts = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(1, -1, 3)
        q = pts @ homography_ab.to(heat_a.dtype).transpose(1, 2)
        q = q[..., :2] / q[..., 2:].clamp_min(1e-8)  # [B, H*W, 2] pixels of B
        hb, wb = heat_b.shape[-2:]
        grid = torch.stack([(q[..., 0] + 0.5) / wb * 2 - 1, (q[..., 1] + 0.5) / hb * 2 - 1], -1).reshape(b, H, W, 2)
        warped = F.grid_sample(heat_b[:, None], grid, align_corners=False)[:, 0]
        valid = (grid.abs() <= 1).all(-1).to(heat_a.dtype)
        if mask_a is not None:
            valid = valid * F.interpolate(mask_a[:, None].to(heat_a.dtype), size=(H, W), mode="nearest")[:, 0]
        p = self.patch
        a = F.unfold((heat_a * valid)[:, None], p, stride=p // 2)  # [B, p*p, L]
        w = F.unfold((warped * valid)[:, None], p, stride=p // 2)
        keep = F.unfold(valid[:, None], p, stride=p // 2).mean(1) >= self.min_valid  # [B, L]
        cos = F.cosine_similarity(a - a.mean(1, keepdim=True), w - w.mean(1, keepdim=True), dim=1, eps=1e-8)
        if not keep.any():
            return heat_a.sum() * 0.0
        return 1 - cos[keep].mean()
