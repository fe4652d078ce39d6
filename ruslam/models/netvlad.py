"""The NetVLAD layer (Arandjelovic et al., CVPR 2016), shared by the NetVLAD teacher and UWNet's global head.

Parameter names follow the public pytorch-NetVLAD / Patch-NetVLAD checkpoints (``conv.weight``, optional
``conv.bias``, ``centroids``) so that their pooling weights load unchanged.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


class NetVLAD(nn.Module):
    """Soft-assignment VLAD pooling: features [B, C, h, w] -> [B, K*C], intra-normalized per cluster, then L2.

    Each location is softly assigned to the K clusters (1x1 conv + softmax); the assignment-weighted residuals to
    the cluster centres are summed over locations. `normalize_input` L2-normalizes each location first, as in the
    paper's implementation.
    """

    def __init__(self, num_clusters: int = 64, dim: int = 128, normalize_input: bool = True, bias: bool = True,
                 intra_eps: float = 1e-12):
        super().__init__()
        # intra_eps > 0 keeps clusters that received (almost) no mass near zero, as in hard VLAD, instead of
        # blowing their residual up to unit length.
        self.intra_eps = intra_eps
        if num_clusters < 1 or dim < 1:
            raise ValueError(f"NetVLAD needs num_clusters >= 1 and dim >= 1, got {num_clusters} and {dim}.")
        self.num_clusters, self.dim, self.normalize_input = num_clusters, dim, normalize_input
        self.conv = nn.Conv2d(dim, num_clusters, kernel_size=1, bias=bias)
        self.centroids = nn.Parameter(torch.rand(num_clusters, dim))

    @property
    def output_dim(self) -> int:
        return self.num_clusters * self.dim

    @torch.no_grad()
    def init_from_centroids(self, centroids: torch.Tensor, alpha: float = 100.0) -> None:
        """Start as hard VLAD around given centres [K, C] (the paper's initialisation, conv = 2*alpha*c)."""
        c = F.normalize(centroids.float(), dim=1) if self.normalize_input else centroids.float()
        self.centroids.copy_(c)
        self.conv.weight.copy_((2.0 * alpha * c)[:, :, None, None])
        if self.conv.bias is not None:
            self.conv.bias.copy_(-alpha * c.norm(dim=1) ** 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or x.shape[1] != self.dim:
            raise ValueError(f"NetVLAD expects features [B, {self.dim}, h, w], got shape {tuple(x.shape)}.")
        if self.normalize_input:
            x = F.normalize(x, dim=1)
        assign = self.conv(x).flatten(2).softmax(dim=1)  # [B, K, N]
        flat = x.flatten(2)  # [B, C, N]
        vlad = torch.einsum("bkn,bcn->bkc", assign, flat) - assign.sum(-1, keepdim=True) * self.centroids
        vlad = F.normalize(vlad, dim=2, eps=self.intra_eps)  # intra-normalization
        return F.normalize(vlad.flatten(1), dim=1)
