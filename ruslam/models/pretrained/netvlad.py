"""NetVLAD (VGG16 + NetVLAD + PCA-whitening to 4096-d), the paper's global teacher, from user-supplied weights.

Accepted weights format: a torch checkpoint readable with ``weights_only=True`` holding either a state dict or
``{"state_dict": state_dict}`` with the layout of the public pytorch-NetVLAD / Patch-NetVLAD Pittsburgh models
(e.g. ``pittsburgh_WPCA4096.pth.tar``):

- ``encoder.<i>.weight/bias``: torchvision VGG16 ``features`` up to conv5_3 (its last ReLU and max-pool removed);
- ``pool.conv.weight`` [64, 512, 1, 1] (no bias) and ``pool.centroids`` [64, 512]: the NetVLAD layer;
- ``WPCA.0.weight`` [4096, 32768, 1, 1] and ``WPCA.0.bias`` [4096]: PCA-whitening as a 1x1 convolution.

If the checkpoint also stores non-tensor entries that ``weights_only`` refuses (e.g. numpy scalars), re-save its
``state_dict`` alone with ``torch.save``. MATLAB ``.mat`` models (the original release) are not read.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
import torchvision

from ruslam.errors import MissingWeights
from ruslam.models.netvlad import NetVLAD
from ruslam.models.weights import load_state_dict, load_strict, resolve_weights

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class NetVLADTeacher(nn.Module):
    """Frozen NetVLAD: image [B, 3, H, W] RGB in [0, 1] -> ``global_descriptor`` [B, pca_dim], unit length."""

    def __init__(
        self,
        weights: str | None = None,
        sha256: str | None = None,
        num_clusters: int = 64,
        pca_dim: int = 4096,
        load: bool = True,
    ):
        super().__init__()
        vgg16_features = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"])  # no classifier
        self.encoder = nn.Sequential(*list(vgg16_features.children())[:-2])
        self.pool = NetVLAD(num_clusters, 512, normalize_input=True, bias=False)
        self.WPCA = nn.Sequential(nn.Conv2d(num_clusters * 512, pca_dim, kernel_size=1))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN)[:, None, None], persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD)[:, None, None], persistent=False)
        if load:
            if weights is None:
                raise MissingWeights(
                    "NetVLADTeacher needs user-supplied weights (pytorch-NetVLAD / Patch-NetVLAD layout, e.g. "
                    "pittsburgh_WPCA4096.pth.tar): pass weights=<path or URL>."
                )
            path = resolve_weights(weights, sha256=sha256)
            load_strict(self, load_state_dict(path), path)
        self.eval().requires_grad_(False)

    def forward(self, image: torch.Tensor, local_outputs: dict | None = None) -> torch.Tensor:
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"NetVLADTeacher expects an RGB batch [B, 3, H, W], got shape {tuple(image.shape)}.")
        vlad = self.pool(self.encoder((image.float() - self.mean) / self.std))
        return F.normalize(self.WPCA(vlad[:, :, None, None]).flatten(1), dim=1)
