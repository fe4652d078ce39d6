"""DANet attention modules (Fu et al., CVPR 2019) used by UWNet's keypoint (FPE) branch.

The position module's affinity over all H*W positions of F1 is (HW)^2: 4,800^2 at 480x640, which alone costs as
much as the whole MobileNetV2 backbone on this CPU (measured ~90 ms). Queries stay at full resolution but keys and
values are average-pooled by ``key_stride`` (4 by default: 4,800 x 300 affinities at 480x640), which keeps the
module's global receptive field at a few ms. ``key_stride=1`` is the original DANet module.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class PositionAttention(nn.Module):
    """DANet PAM: out = x + gamma * V softmax(Q^T K); gamma starts at 0 so the module starts as identity."""

    def __init__(self, channels: int, reduction: int = 8, key_stride: int = 4):
        super().__init__()
        inner = max(channels // reduction, 1)
        self.query = nn.Conv2d(channels, inner, 1)
        self.key = nn.Conv2d(channels, inner, 1)
        self.value = nn.Conv2d(channels, channels, 1)
        self.gamma = nn.Parameter(torch.zeros(1))
        self.key_stride = key_stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        kv = x
        if self.key_stride > 1:
            kv = F.avg_pool2d(x, self.key_stride, ceil_mode=True)
        q = self.query(x).flatten(2).transpose(1, 2)  # [B, HW, c']
        k = self.key(kv).flatten(2)  # [B, c', M]
        v = self.value(kv).flatten(2).transpose(1, 2)  # [B, M, C]
        attn = torch.softmax(torch.bmm(q, k), dim=-1)  # [B, HW, M]
        out = torch.bmm(attn, v).transpose(1, 2).reshape(b, c, h, w)
        return x + self.gamma * out


class ChannelAttention(nn.Module):
    """DANet CAM: C x C affinity of the channels, computed as max(energy) - energy as in the reference code."""

    def __init__(self):
        super().__init__()
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        flat = x.flatten(2)  # [B, C, HW]
        energy = torch.bmm(flat, flat.transpose(1, 2))
        energy = energy.amax(dim=-1, keepdim=True) - energy
        out = torch.bmm(torch.softmax(energy, dim=-1), flat).reshape(b, c, h, w)
        return x + self.gamma * out


class DualAttention(nn.Module):
    """Position and channel attention in parallel on the same map, fused by element-wise sum (DANet)."""

    def __init__(self, channels: int, reduction: int = 8, key_stride: int = 4):
        super().__init__()
        self.position = PositionAttention(channels, reduction, key_stride)
        self.channel = ChannelAttention()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.position(x) + self.channel(x)
