"""Correspondence loss between two warped views of one image: descriptors trained to be told apart.

Eq. 8 only asks the student to copy the teacher's descriptors; matching needs the descriptor of a point to be
nearer its own correspondence than any other point of the other view, whatever water and rotation each view got.
As in XFeat's and ALIKED's training: sample up to ``num_samples`` valid cells of view A, map their centres into
view B with the known homography, read B's descriptors there (bilinear), and apply a symmetric InfoNCE
(dual-softmax) over the A x B similarity matrix, negatives being the other sampled points of the same image.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ruslam.models.extractor import sample_dense

CELL = 8


def cell_centres(h: int, w: int, device=None) -> torch.Tensor:
    """Pixel centres [h*w, 2] (x, y) of the 1/8 cells, row-major: cell u covers pixels [8u, 8u+8)."""
    ys, xs = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    return torch.stack([xs, ys], -1).reshape(-1, 2).float() * CELL + (CELL - 1) / 2


def transfer(points: torch.Tensor, homography: torch.Tensor) -> torch.Tensor:
    """Points [N, 2] through a 3x3 homography."""
    ph = torch.cat([points, torch.ones_like(points[:, :1])], 1) @ homography.to(points.dtype).T
    return ph[:, :2] / ph[:, 2:].clamp_min(1e-8)


class CorrespondenceLoss(nn.Module):
    def __init__(self, temperature: float = 0.05, num_samples: int = 256, border: float = 4.0):
        super().__init__()
        if temperature <= 0 or num_samples < 2:
            raise ValueError(f"CorrespondenceLoss needs temperature > 0 and num_samples >= 2, got {temperature}, "
                             f"{num_samples}.")
        self.temperature, self.num_samples, self.border = temperature, num_samples, border

    def forward(self, desc_a: torch.Tensor, desc_b: torch.Tensor, homography_ab: torch.Tensor,
                mask_a: torch.Tensor | None = None) -> torch.Tensor:
        """desc_a, desc_b [B, D, h, w] unit descriptors of the two views; homography_ab [B, 3, 3] maps view-A
        pixels to view-B pixels; mask_a [B, h, w] valid cells of A (content of the image, not warped-in border).
        Returns the mean over images that have at least 2 shared points (0 if none has)."""
        return self.loss(desc_a, self.sample(desc_a, desc_b, homography_ab, mask_a))

    def sample(self, desc_a: torch.Tensor, desc_b: torch.Tensor, homography_ab: torch.Tensor,
               mask_a: torch.Tensor | None = None) -> list[tuple[int, torch.Tensor, torch.Tensor]]:
        """(image i, sampled cells idx of A [N] (row-major), cosine similarities [N, N] of A's cells to B's
        descriptors at their correspondences) for every image with at least 2 shared points."""
        b, _, h, w = desc_a.shape
        centres = cell_centres(h, w, desc_a.device)
        hb, wb = desc_b.shape[-2] * CELL, desc_b.shape[-1] * CELL
        samples = []
        for i in range(b):
            q = transfer(centres, homography_ab[i])
            ok = ((q[:, 0] >= self.border) & (q[:, 0] <= wb - 1 - self.border)
                  & (q[:, 1] >= self.border) & (q[:, 1] <= hb - 1 - self.border))
            if mask_a is not None:
                ok &= mask_a[i].reshape(-1) > 0.5
            idx = ok.nonzero()[:, 0]
            if len(idx) < 2:
                continue
            if len(idx) > self.num_samples:
                idx = idx[torch.randperm(len(idx), device=idx.device)[: self.num_samples]]
            da = desc_a[i].flatten(1)[:, idx].T  # [N, D]
            db = F.normalize(sample_dense(desc_b[i : i + 1], q[idx][None], CELL)[0], dim=1)
            samples.append((i, idx, da @ db.T))
        return samples

    def loss(self, desc_a: torch.Tensor, samples: list) -> torch.Tensor:
        """Symmetric InfoNCE over the samples of `sample`."""
        losses = []
        for _, idx, cos in samples:
            sim = cos / self.temperature
            target = torch.arange(len(idx), device=sim.device)
            losses.append(0.5 * (F.cross_entropy(sim, target) + F.cross_entropy(sim.T, target)))
        if not losses:
            return desc_a.sum() * 0.0
        return torch.stack(losses).mean()
