"""Multi-task distillation loss, paper eq. 8 (uncertainty weighting of Kendall et al., as HF-Net).

L = e^-a L1 + e^-b L2 + 2 e^-g L3 + a + b + g, with a, b, g learned:
L1 squared L2 distance of the global descriptors, L2 squared L2 distance of the dense local descriptors averaged
over valid cells, L3 cross-entropy of the student's 65-way cell distribution against the teacher's softmax (soft
labels, dustbin included) averaged over valid cells (a finer-cell student's 17-way 4x4 cells against the teacher's
cells rewritten as sub-cells, `subcell_targets`). Valid cells are those a geometric augmentation kept inside the
image (mask), so warped-in borders teach nothing.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class DistillationLoss(nn.Module):
    def __init__(self, detector_weight: float = 2.0):
        super().__init__()
        self.alpha = nn.Parameter(torch.zeros(()))  # global
        self.beta = nn.Parameter(torch.zeros(()))  # local descriptors
        self.gamma = nn.Parameter(torch.zeros(()))  # detector
        self.detector_weight = detector_weight

    @staticmethod
    def terms(pred: dict, target: dict, mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The three unweighted losses; mask [B, h, w] of valid cells (1 = valid), all valid when None."""
        logits = pred["keypoint_logits"].float()
        desc = pred["dense_descriptors"].float()
        if mask is None:
            mask = desc.new_ones(desc.shape[0], *desc.shape[2:])
        mask = mask.to(desc.dtype)
        denom = mask.sum().clamp_min(1.0)
        glob = (pred["global_descriptor"].float() - F.normalize(target["global_descriptor"].float(), dim=-1))
        glob = glob.pow(2).sum(-1).mean()
        t_desc = F.normalize(target["dense_descriptors"].float(), dim=1)
        local = ((desc - t_desc).pow(2).sum(1) * mask).sum() / denom
        t_logits = target["keypoint_logits"].float()
        if t_logits.shape[1] != logits.shape[1]:  # a finer-cell student: the teacher's 8x8 cells as sub-cells
            from ruslam.models.extractor import logits_cell  # noqa: PLC0415
            from ruslam.models.uwnet_xfeat_student import subcell_targets  # noqa: PLC0415

            t_logits, mask = subcell_targets(t_logits, mask, logits_cell(logits))
        if mask.shape[-2:] != logits.shape[-2:]:  # finer-cell targets given as such (`fine_teacher`)
            mask = F.interpolate(mask[:, None], size=logits.shape[-2:], mode="nearest")[:, 0]
        soft = t_logits.softmax(dim=1)
        ce = -(soft * logits.log_softmax(dim=1)).sum(1)
        detector = (ce * mask).sum() / mask.sum().clamp_min(1.0)
        return {"global": glob, "local": local, "detector": detector}

    def forward(self, pred: dict, target: dict, mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        t = self.terms(pred, target, mask)
        total = (
            torch.exp(-self.alpha) * t["global"]
            + torch.exp(-self.beta) * t["local"]
            + self.detector_weight * torch.exp(-self.gamma) * t["detector"]
            + self.alpha + self.beta + self.gamma
        )
        return {"total": total, **t, "alpha": self.alpha.detach(), "beta": self.beta.detach(),
                "gamma": self.gamma.detach()}
