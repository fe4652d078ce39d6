"""SuperPoint (DeTone et al., 2018), the paper's local teacher, with magicleap-compatible weights.

The module names (``conv1a`` ... ``convDb``) and shapes equal the public ``superpoint_v1.pth`` of
magicleap/SuperPointPretrainedNetwork, so that file loads strictly. Those weights cannot be downloaded on an
offline machine: pass a local path, or a URL (+ sha256) fetched once into the weights cache.
Input: grey image in [0, 1] (ITU-R BT.601 from RGB, as the reference demo reads images with OpenCV).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ruslam.errors import MissingWeights
from ruslam.models.extractor import Extractor, decode_sparse, to_gray
from ruslam.models.weights import default_cache_dir, load_state_dict, load_strict, resolve_weights

MAGICLEAP_URL = "https://github.com/magicleap/SuperPointPretrainedNetwork/raw/master/superpoint_v1.pth"
STRIDE = 8
_GREY = (0.299, 0.587, 0.114)


class SuperPointNet(nn.Module):
    """The magicleap architecture: shared VGG-style encoder to 1/8, detector (65 cell logits), descriptor (256-d)."""

    def __init__(self):
        super().__init__()
        c1, c2, c3, c4, c5, d1 = 64, 64, 128, 128, 256, 256
        self.conv1a, self.conv1b = nn.Conv2d(1, c1, 3, padding=1), nn.Conv2d(c1, c1, 3, padding=1)
        self.conv2a, self.conv2b = nn.Conv2d(c1, c2, 3, padding=1), nn.Conv2d(c2, c2, 3, padding=1)
        self.conv3a, self.conv3b = nn.Conv2d(c2, c3, 3, padding=1), nn.Conv2d(c3, c3, 3, padding=1)
        self.conv4a, self.conv4b = nn.Conv2d(c3, c4, 3, padding=1), nn.Conv2d(c4, c4, 3, padding=1)
        self.convPa, self.convPb = nn.Conv2d(c4, c5, 3, padding=1), nn.Conv2d(c5, 65, 1)
        self.convDa, self.convDb = nn.Conv2d(c4, c5, 3, padding=1), nn.Conv2d(c5, d1, 1)

    def forward(self, grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """grey [B, 1, H, W] in [0, 1] -> (logits [B, 65, H/8, W/8], raw descriptors [B, 256, H/8, W/8])."""
        x = grey
        for a, b in [(self.conv1a, self.conv1b), (self.conv2a, self.conv2b), (self.conv3a, self.conv3b)]:
            x = F.max_pool2d(F.relu(b(F.relu(a(x)))), 2)
        x = F.relu(self.conv4b(F.relu(self.conv4a(x))))
        return self.convPb(F.relu(self.convPa(x))), self.convDb(F.relu(self.convDa(x)))


def load_superpoint_net(weights: str | None, sha256: str | None = None, cache_dir: str | None = None):
    """A `SuperPointNet` with weights from a path or URL; without weights, one sentence on where to put them."""
    net = SuperPointNet()
    if weights is None:
        cached = (default_cache_dir() if cache_dir is None else Path(cache_dir)) / "superpoint_v1.pth"
        if not cached.is_file():
            raise MissingWeights(
                f"SuperPoint needs the magicleap superpoint_v1.pth weights: put the file at {cached} or pass "
                f"weights=<path or URL> (e.g. {MAGICLEAP_URL})."
            )
        weights = str(cached)
    path = resolve_weights(weights, sha256=sha256, cache_dir=cache_dir)
    load_strict(net, load_state_dict(path), path)
    return net.eval().requires_grad_(False)


class SuperPointTeacher(nn.Module):
    """Frozen SuperPoint: image [B, 3, H, W] in [0, 1] (H, W multiples of 8) -> dense targets at 1/8.

    Returns ``keypoint_logits`` [B, 65, H/8, W/8] and ``dense_descriptors`` [B, 256, H/8, W/8] (unit length).
    """

    descriptor_dim = 256

    def __init__(self, weights: str | None = None, sha256: str | None = None, net: SuperPointNet | None = None):
        super().__init__()
        self.net = net if net is not None else load_superpoint_net(weights, sha256)
        self.net.eval().requires_grad_(False)

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        if image.ndim != 4 or image.shape[1] not in (1, 3):
            raise ValueError(f"SuperPointTeacher expects an image batch [B, 3, H, W], got {tuple(image.shape)}.")
        if image.shape[-2] % STRIDE or image.shape[-1] % STRIDE:
            raise ValueError(f"SuperPointTeacher expects H and W multiples of 8, got {tuple(image.shape[-2:])}.")
        grey = image.float() if image.shape[1] == 1 else (image.float() * image.new_tensor(_GREY)[:, None, None])
        logits, desc = self.net(grey.sum(1, keepdim=True))
        return {"keypoint_logits": logits, "dense_descriptors": F.normalize(desc, dim=1)}


class SuperPoint(Extractor):
    """Sparse SuperPoint through the project's post-processing (softmax, dustbin dropped, pixel shuffle, NMS,
    border removal, top-k, bilinear descriptor sampling with the one convention, L2)."""

    default_conf = {
        "max_keypoints": 2000,
        "detection_threshold": 0.005,
        "nms_radius": 4,
        "border": 4,
        "weights": None,
        "sha256": None,
        "device": "cpu",
    }
    uses_device = True

    def __init__(self, net: SuperPointNet | None = None, **conf):
        super().__init__(**conf)
        self.device = torch.device(self.conf["device"])
        if net is None:
            net = load_superpoint_net(self.conf["weights"], self.conf["sha256"])
        self.net = net.to(self.device).eval()

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        grey = to_gray(image)
        h, w = grey.shape
        x = torch.from_numpy(grey)[None, None].to(self.device)
        x = F.pad(x, (0, -w % STRIDE, 0, -h % STRIDE), mode="replicate")  # cell layout needs multiples of 8
        logits, desc = self.net(x)
        xy, scores, descriptors = decode_sparse(logits, desc, (h, w), self.conf, STRIDE)
        return {
            "keypoints": xy.cpu().numpy().astype(np.float32),
            "scores": scores.cpu().numpy().astype(np.float32),
            "descriptors": descriptors.cpu().numpy().astype(np.float32),
        }
