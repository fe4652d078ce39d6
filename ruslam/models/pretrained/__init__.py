"""Frozen third-party networks: the teachers of the distillation (paper 3.2) and the baselines UWNet is compared with.

- `xfeat.py` (XFeat), `superpoint.py` (SuperPoint): each a teacher module and an extractor (`load_extractor`);
  `aliked_disk.py`: ALIKED and DISK extractors; `aliked_keypoints.py`: ALIKED's score map as a keypoint teacher;
  `vlad.py`, `netvlad.py`: the global teachers.
- `Teacher` pairs a local and a global teacher into the one module the cache runs: image [B, 3, H, W] in [0, 1]
  -> ``keypoint_logits`` [B, 65, H/8, W/8], ``dense_descriptors`` [B, D, H/8, W/8], ``global_descriptor`` [B, G].
  Offline default: XFeat + VLAD (`conf/teacher/xfeat_vlad.yaml`); paper: SuperPoint + NetVLAD.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn as nn


class Teacher(nn.Module):
    """`local(image) -> {keypoint_logits, dense_descriptors}` plus `global_head(image, local_outputs) -> [B, G]`."""

    def __init__(self, local: nn.Module, global_head: nn.Module):
        super().__init__()
        self.local, self.global_head = local, global_head
        self.eval().requires_grad_(False)

    def train(self, mode: bool = True):  # frozen: never leaves eval mode
        return super().train(False)

    @property
    def descriptor_dim(self) -> int:
        return self.local.descriptor_dim

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        out = dict(self.local(image))
        out["global_descriptor"] = self.global_head(image, out)
        return out

    def prepare(self, dataset, cache_dir: str | Path) -> None:
        """Fit what depends on the training data (the VLAD codebook, saved beside the cache) before caching."""
        if hasattr(self.global_head, "prepare"):
            self.global_head.prepare(self.local, dataset, cache_dir)
