"""`UWNetExtractor`: a trained UWNet behind the project's extractor contract (`load_extractor("uwnet_xfeat")`).

The working size: an image with fewer than ``min_pixels`` pixels is upsampled to that area (aspect kept), a larger
one runs at its own resolution (``resize_min`` / ``resize_max`` bound the longer side where set); both sides are
then multiples of 8 (the cell layout). Keypoints are mapped back to input pixels with the pixel-centre convention
x = (x' + 0.5) * s - 0.5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ruslam.errors import InputError
from ruslam.models.export import load_uwnet
from ruslam.models.extractor import (
    Extractor,
    check_longer_side,
    decode_sparse,
    to_float_rgb,
)

STRIDE = 8
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
SHIPPED_WEIGHTS = WEIGHTS_DIR / "uwnet_xfeat.pt"  # the better of the two trained variants (README)


class UWNetExtractor(Extractor):
    default_conf = {
        "weights": None,  # None: the checkpoint shipped in ruslam/weights/uwnet_xfeat.pt
        "descriptor_dim": None,  # set to refuse weights of another descriptor width
        "max_keypoints": 2000,
        "nms_radius": 2,  # XFeat's 5x5 window, as the teacher; a 9x9 max-pool at 480x640 costs ~1/3 of the backbone
        "detection_threshold": 0.005,
        "border": 4,
        # The working size as a pixel area: 8 px cells are coarse, so smaller images are upsampled to 672x504's
        # area (the largest within 1.3x XFeat's time at 640x480; each step up buys matching precision for time,
        # docs/training.md, "Working size"); larger frames keep every pixel (a wide 1241x376 frame is not shrunk
        # to a 672 px side). resize_min / resize_max: optional bounds on the longer side (None: none).
        "min_pixels": 672 * 504,
        "resize_min": None,
        "resize_max": None,
        "subpixel_radius": 4,  # keypoints at the heat's centre in their 9x9 window (0: integer pixels)
        "device": "cpu",
    }
    uses_device = True
    default_weights = SHIPPED_WEIGHTS

    def __init__(self, **conf):
        super().__init__(**conf)
        for key in ("resize_min", "resize_max"):
            check_longer_side("UWNet", key, self.conf[key])
        area = self.conf["min_pixels"]
        if area is not None and not (isinstance(area, int | float) and 256 <= area <= 4096**2):
            raise InputError(f"UWNet min_pixels must be null or a pixel area (256-16777216), got {area!r}.")
        weights = self.conf["weights"] or self.default_weights
        self.device = torch.device(self.conf["device"])
        self.net = load_uwnet(weights, descriptor_dim=self.conf["descriptor_dim"]).to(self.device)
        self.descriptor_dim = self.net.config["descriptor_dim"]

    @classmethod
    def from_file(cls, path: str | Path, device: str = "cpu", **conf) -> UWNetExtractor:
        return cls(weights=str(path), device=device, **conf)

    def _input_size(self, h: int, w: int) -> tuple[int, int]:
        scale = 1.0
        if self.conf["resize_max"] and max(h, w) > self.conf["resize_max"]:
            scale = self.conf["resize_max"] / max(h, w)
        elif self.conf["resize_min"] and max(h, w) < self.conf["resize_min"]:
            scale = self.conf["resize_min"] / max(h, w)
        elif self.conf["min_pixels"] and h * w < self.conf["min_pixels"]:
            scale = float(np.sqrt(self.conf["min_pixels"] / (h * w)))
        return max(STRIDE, round(h * scale / STRIDE) * STRIDE), max(STRIDE, round(w * scale / STRIDE) * STRIDE)

    @torch.inference_mode()
    def run(self, image: np.ndarray) -> tuple[dict[str, torch.Tensor], tuple[int, int], tuple[int, int]]:
        """The network's outputs on the image at the working size, the input (h, w) and the working (h, w)."""
        rgb = to_float_rgb(image)
        h, w = rgb.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].to(self.device)
        nh, nw = self._input_size(h, w)
        if (nh, nw) != (h, w):
            x = F.interpolate(x, size=(nh, nw), mode="bilinear", align_corners=False, antialias=nh < h)
        return self.net(x.clamp(0, 1)), (h, w), (nh, nw)

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        out, (h, w), (nh, nw) = self.run(image)
        xy, scores, desc = decode_sparse(out["keypoint_logits"], out["dense_descriptors"], (nh, nw), self.conf,
                                         STRIDE, out.get("reliability"))
        scale = xy.new_tensor([w / nw, h / nh])
        xy = (xy + 0.5) * scale - 0.5
        return {
            "keypoints": xy.cpu().numpy().astype(np.float32),
            "scores": scores.cpu().numpy().astype(np.float32),
            "descriptors": desc.cpu().numpy().astype(np.float32),
            "global_descriptor": out["global_descriptor"][0].cpu().numpy().astype(np.float32),
        }


class UWNetFineCellExtractor(UWNetExtractor):
    """UWNet with 4x4 keypoint cells (`load_extractor("uwnet_xfeat_s4")`, `XFeatStudent(keypoint_cell=4)`):
    keypoints from a 17-way softmax per 4x4 cell, descriptors sampled from the 1/8 map at the keypoints
    (docs/finer_cells.md)."""

    default_weights = WEIGHTS_DIR / "uwnet_xfeat_s4.pt"


class UWNetMobileNetExtractor(UWNetExtractor):
    """The other trained variant, (a): the paper's MobileNetV2 UWNet from ImageNet weights
    (`load_extractor("uwnet_mobilenet")`)."""

    default_weights = WEIGHTS_DIR / "uwnet_mobilenet.pt"
    default_conf = {**UWNetExtractor.default_conf, "min_pixels": None, "resize_max": 640}  # as it was measured
