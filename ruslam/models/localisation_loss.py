"""Localisation loss: a keypoint of one training view, warped into the other, must be found there to the pixel.

Matching at 3 px rewards keypoints that repeat precisely. Of the student's matches 3-10 px off (tune set, 0-30°),
three in four had no keypoint within 3 px of the true spot: the counterpart was detected, but a few pixels away
(ALIKED's near misses are mostly the other kind, a neighbour picked; BENCHMARKS.md). This term measures that
directly and the way the extractor sees it: view A's strongest peaks are refined as `decode_sparse` refines them
(`refine_subpixel`, the heat-weighted centre of a window), warped into view B by the known homography, and B's
heat is refined from the nearest pixel there; the distance between the two is the loss, both ways, each
keypoint's error clipped at `max_error` pixels (a peak with no counterpart gives no gradient). Both views receive
the gradient through their windows' weights (after ALIKED's reprojection loss, Zhao et al. 2023).
"""

from __future__ import annotations

import torch
from torch import nn

from ruslam.models.extractor import cell_logits_to_heatmap, detect_keypoints, refine_subpixel


class LocalisationLoss(nn.Module):
    def __init__(self, radius: int = 4, nms_radius: int = 2, min_score: float = 0.005, top_k: int = 256,
                 max_error: float = 4.0):
        """radius, nms_radius, min_score: the extractor's subpixel_radius, nms_radius and detection_threshold."""
        super().__init__()
        if radius < 1 or nms_radius < 0 or min_score < 0 or top_k < 1 or max_error <= 0:
            raise ValueError(f"LocalisationLoss needs radius >= 1, nms_radius >= 0, min_score >= 0, top_k >= 1 and "
                             f"max_error > 0, got {radius}, {nms_radius}, {min_score}, {top_k}, {max_error}.")
        self.radius, self.nms_radius, self.min_score = radius, nms_radius, min_score
        self.top_k, self.max_error = top_k, max_error

    def forward(self, logits_a: torch.Tensor, logits_b: torch.Tensor, homography_ab: torch.Tensor,
                mask_a: torch.Tensor | None = None, mask_b: torch.Tensor | None = None) -> torch.Tensor:
        """logits_a, logits_b [B, 65, h, w] cell logits; homography_ab [B, 3, 3] maps view-A pixels to view-B
        pixels; mask_a, mask_b [B, h, w] valid cells. Returns the mean clipped distance in pixels (0 without
        keypoints)."""
        heat_a, heat_b = cell_logits_to_heatmap(logits_a), cell_logits_to_heatmap(logits_b)
        h_ab = homography_ab.to(heat_a.dtype)
        errors = [*self._one_way(heat_a, heat_b, h_ab, mask_a, mask_b),
                  *self._one_way(heat_b, heat_a, torch.linalg.inv(h_ab), mask_b, mask_a)]
        errors = torch.cat(errors) if errors else heat_a.new_zeros(0)
        if len(errors) == 0:
            return heat_a.sum() * 0.0
        return errors.clamp(max=self.max_error).mean()

    def _one_way(self, heat_a, heat_b, homography, mask_a, mask_b) -> list[torch.Tensor]:
        r = self.radius
        with torch.no_grad():
            found = detect_keypoints(heat_a.detach(), self.nms_radius, self.min_score, self.top_k, r)
        hb, wb = heat_b.shape[-2:]
        out = []
        for i, (xy, _) in enumerate(found):
            if mask_a is not None:
                xy = xy[_valid(mask_a[i], xy)]
            if len(xy) == 0:
                continue
            centre_a = refine_subpixel(heat_a[i], xy, r)
            p = torch.cat([centre_a, torch.ones_like(centre_a[:, :1])], 1) @ homography[i].T
            p = p[:, :2] / p[:, 2:].clamp_min(1e-8)
            start = p.detach().round()
            inside = ((start[:, 0] >= r) & (start[:, 0] < wb - r) & (start[:, 1] >= r) & (start[:, 1] < hb - r))
            if mask_b is not None:
                inside &= _valid(mask_b[i], start.clamp(min=0))
            if inside.any():
                centre_b = refine_subpixel(heat_b[i], start[inside], r)
                out.append((centre_b - p[inside]).norm(dim=1))
        return out


def _valid(mask_cells: torch.Tensor, xy: torch.Tensor, cell: int = 8) -> torch.Tensor:
    """Whether each pixel (x, y) lies in a valid cell of ``mask_cells`` [h, w] (False outside it)."""
    cx, cy = (xy[:, 0] // cell).long(), (xy[:, 1] // cell).long()
    h, w = mask_cells.shape
    ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
    valid = torch.zeros(len(xy), dtype=torch.bool, device=xy.device)
    valid[ok] = mask_cells[cy[ok], cx[ok]].bool()
    return valid
