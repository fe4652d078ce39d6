"""UWNet as torch modules for learned-feature pipelines (kornia, LightGlue) and its ONNX graph with the decode.

- `UWNetFeatures` (kornia style, an `nn.Module`): ``forward(images [B, C, H, W])`` -> one dict per image with
  ``keypoints`` [N, 2], ``scores`` [N], ``descriptors`` [N, D]; ``dense(images)`` -> the network's dense maps.
  The dense part (backbone, heads) is differentiable with respect to the network's weights (fine-tuning; XFeat's
  input normalisation runs without gradients, so none reach the pixels); so are the descriptors sampled at the
  keypoints (bilinear, `sample_descriptors`) and the sub-pixel keypoint offsets (a heat-weighted centroid). Which
  pixels are keypoints (NMS, threshold, top-k) is a discrete choice and carries no gradient.
- ``UWNetFeatures.extract(image)`` (LightGlue style, without gradients): ``image`` [B, C, H, W] or [C, H, W] ->
  ``keypoints`` [B, N, 2], ``keypoint_scores`` [B, N], ``descriptors`` [B, N, D], ``image_size`` [B, 2] (w, h), and
  ``global_descriptor`` [B, G]. A batch keeps the same N for every image: the best min(N_i) of each.
- `export_onnx` writes the dense network for a fixed H x W (dynamic batch) with outputs ``keypoint_logits``,
  ``dense_descriptors``, ``global_descriptor`` and, for the XFeat-based UWNet, ``reliability``; `decode_onnx`
  turns those arrays into the keypoints, scores and descriptors that `UWNetFeatures` gives for the same input.

Conventions as everywhere in the project: images RGB (grey is replicated) in [0, 1]; keypoints (x, y) in pixels
of the input image with pixel centres at integer coordinates. Images are resized to `UWNetExtractor`'s working
size (sides multiples of 8) and keypoints mapped back with x = (x' + 0.5) * s - 0.5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ruslam.atomic_files import atomic_path
from ruslam.errors import InputError
from ruslam.models.export import load_uwnet
from ruslam.models.extractor import Extractor, check_longer_side, decode_sparse
from ruslam.models.uwnet_extractor import SHIPPED_WEIGHTS, STRIDE, UWNetExtractor

DECODE_KEYS = ("max_keypoints", "nms_radius", "detection_threshold", "border", "subpixel_radius")
DEFAULTS = {k: UWNetExtractor.default_conf[k] for k in DECODE_KEYS}


class UWNetFeatures(nn.Module):
    """UWNet (shipped ``uwnet_xfeat`` weights by default, or a weights file) as a batched torch module.

    Options are `UWNetExtractor`'s (``max_keypoints``, ``detection_threshold``, ``nms_radius``, the working size
    ``min_pixels`` / ``resize_min`` / ``resize_max``, ...), with the same defaults, so both give the same
    keypoints for the same image; ``min_pixels=None`` runs at the images' own size."""

    def __init__(self, weights: str | Path | None = None, **conf):
        super().__init__()
        if "device" in conf:
            raise InputError("UWNetFeatures takes no device option: move the module with .to(device).")
        self.sizing = UWNetExtractor.__new__(UWNetExtractor)  # its options and working size, without a second net
        Extractor.__init__(self.sizing, **conf)
        for key in ("resize_min", "resize_max"):
            check_longer_side("UWNetFeatures", key, self.sizing.conf[key])
        self.conf = {k: self.sizing.conf[k] for k in DECODE_KEYS}
        self.net = load_uwnet(weights or SHIPPED_WEIGHTS, descriptor_dim=self.sizing.conf["descriptor_dim"])

    def _prepare(self, images: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        if images.ndim == 3:
            images = images[None]
        if images.ndim != 4 or images.shape[1] not in (1, 3):
            raise InputError(f"images must be [B, 1 or 3, H, W] (or [C, H, W]), got {tuple(images.shape)}.")
        if min(images.shape[-2:]) < 16:
            raise InputError(f"images must be at least 16x16 pixels, got {tuple(images.shape[-2:])}.")
        images = images.float()
        if images.shape[1] == 1:
            images = images.expand(-1, 3, -1, -1)
        h, w = images.shape[-2:]
        nh, nw = self.sizing._input_size(h, w)
        if (nh, nw) != (h, w):
            images = F.interpolate(images, size=(nh, nw), mode="bilinear", align_corners=False, antialias=nh < h)
        return images.clamp(0, 1), (h, w)

    def dense(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        """The network's dense outputs at the working size (differentiable): ``keypoint_logits`` [B, 65, h, w],
        ``dense_descriptors`` [B, D, h, w], ``global_descriptor`` [B, G], and ``reliability`` for the XFeat UWNet."""
        x, _ = self._prepare(images)
        return self.net(x)

    def forward(self, images: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        x, (h, w) = self._prepare(images)
        out = self.net(x)
        nh, nw = x.shape[-2:]
        return decode_batch(out, (nh, nw), (h, w), self.conf)

    @torch.no_grad()
    def extract(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """LightGlue's extractor interface (batched, same N per image; inference, no gradients)."""
        feats = self(image)
        h, w = (image.shape[-2:])
        n = min(len(f["keypoints"]) for f in feats)
        out = {"keypoints": torch.stack([f["keypoints"][:n] for f in feats]),
               "keypoint_scores": torch.stack([f["scores"][:n] for f in feats]),
               "descriptors": torch.stack([f["descriptors"][:n] for f in feats]),
               "global_descriptor": torch.stack([f["global_descriptor"] for f in feats])}
        out["image_size"] = out["keypoints"].new_tensor([[w, h]]).expand(len(feats), 2)
        return out


def decode_batch(out: dict[str, torch.Tensor], work: tuple[int, int], size: tuple[int, int],
                 conf: dict) -> list[dict[str, torch.Tensor]]:
    """Dense outputs of a batch at the working size ``work`` -> per image keypoints in the ``size`` (h, w) input,
    scores (best first) and unit descriptors; the same decoding as `UWNetExtractor.extract`."""
    (nh, nw), (h, w) = work, size
    feats = []
    for b in range(out["keypoint_logits"].shape[0]):
        rel = out.get("reliability")
        xy, scores, desc = decode_sparse(out["keypoint_logits"][b:b + 1], out["dense_descriptors"][b:b + 1],
                                         (nh, nw), conf, STRIDE, None if rel is None else rel[b:b + 1])
        xy = (xy + 0.5) * xy.new_tensor([w / nw, h / nh]) - 0.5
        feats.append({"keypoints": xy, "scores": scores, "descriptors": desc,
                      "global_descriptor": out["global_descriptor"][b]})
    return feats


# ----------------------------------------------------------------------------------------------------------- ONNX


class _DenseOutputs(nn.Module):
    """The network's outputs as a tuple. The XFeat UWNet pads its input to multiples of 32 (reflection, bottom and
    right); done here with constant amounts for the export size, so the graph has static shapes throughout."""

    def __init__(self, net: nn.Module, names: tuple[str, ...], height: int, width: int):
        super().__init__()
        self.net, self.names = net, names
        multiple = 32 if getattr(net, "architecture", "") == "xfeat_student" else 1
        self.pad = (0, -width % multiple, 0, -height % multiple)
        self.size, self.cells = (height, width), (height // STRIDE, width // STRIDE)

    def forward(self, image):
        for dim, n, pad in ((-2, self.size[0], self.pad[3]), (-1, self.size[1], self.pad[1])):
            if pad:  # reflection as a gather of constant indices (ONNX's Pad would leave H and W unknown to Unfold)
                idx = torch.cat([torch.arange(n), torch.arange(n - 2, n - 2 - pad, -1)])
                image = image.index_select(dim, idx)
        out = self.net(image)
        hc, wc = self.cells
        out = {k: v if v.ndim == 2 else v[..., :hc, :wc] for k, v in out.items()}
        if any(self.pad):  # the global descriptor pools the cells of the image only, as without the padding
            vlad = self.net.netvlad(out["dense_descriptors"].contiguous())
            vlad = vlad.sign() * (vlad.abs() + 1e-6).pow(self.net.vlad_power)
            out["global_descriptor"] = F.normalize(vlad, dim=-1)
        return tuple(out[k] for k in self.names)


def onnx_output_names(net: nn.Module) -> tuple[str, ...]:
    probe = net(torch.rand(1, 3, 32, 32))
    return tuple(k for k in ("keypoint_logits", "dense_descriptors", "global_descriptor", "reliability") if k in probe)


def export_onnx(module: UWNetFeatures, path: str | Path, height: int = 480, width: int = 640,
                opset: int = 17) -> Path:
    """The dense network as ONNX for input ``image`` [B, 3, height, width] (multiples of 8, RGB in [0, 1])."""
    if height % STRIDE or width % STRIDE:
        raise InputError(f"ONNX input size must be multiples of {STRIDE}, got {height}x{width}.")
    net = module.net.eval()
    with torch.no_grad():
        names = onnx_output_names(net)
        wrapper = _DenseOutputs(net, names, height, width).eval()
        with atomic_path(path) as tmp:
            torch.onnx.export(wrapper, (torch.rand(1, 3, height, width),), str(tmp), input_names=["image"],
                              output_names=list(names), opset_version=opset, dynamic_axes={"image": {0: "batch"}},
                              dynamo=False)
    return Path(path)


def decode_onnx(outputs: dict[str, np.ndarray], size: tuple[int, int] | None = None,
                conf: dict | None = None) -> list[dict[str, np.ndarray]]:
    """ONNX outputs (name -> array) of a [B, 3, h, w] input -> per image ``keypoints`` [N, 2], ``scores``,
    ``descriptors`` [N, D], ``global_descriptor``; keypoints in an original (h, w) ``size`` the input was resized
    from (None: the network input itself)."""
    t = {k: torch.from_numpy(np.asarray(v)) for k, v in outputs.items()}
    nh, nw = (t["keypoint_logits"].shape[-2] * STRIDE, t["keypoint_logits"].shape[-1] * STRIDE)
    feats = decode_batch(t, (nh, nw), size or (nh, nw), {**DEFAULTS, **(conf or {})})
    return [{k: v.numpy() for k, v in f.items()} for f in feats]
