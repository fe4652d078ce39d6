"""The one extractor contract of the project (hloc/LightGlue style) and its shared conventions.

Every extractor (ORB, SIFT, XFeat, SuperPoint, UWNet) subclasses `Extractor`: a `default_conf` dict merged with
keyword overrides, and `extract(image) -> dict` with stable keys:

- ``keypoints``  float32 [N, 2], (x, y) in pixels of the *input* image, pixel centres at integer coordinates;
- ``scores``     float32 [N];
- ``descriptors`` [N, D], float32 L2-normalized, or uint8 packed bits for binary descriptors (ORB);
- ``global_descriptor`` float32 [G] L2-normalized, only for extractors that have a global head;
- ``scales``     float32 [N], the pyramid scale each keypoint was detected at (1 = full size), only for
  pyramid detectors (ORB): the SLAM widens a keypoint's search window by it.

Dense descriptor maps at stride ``s`` are sampled at keypoints with the convention
``(kp + 0.5) / s - 0.5`` and ``align_corners=False`` (`sample_descriptors`), used everywhere in the project.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ruslam.errors import InputError


class Extractor:
    default_conf: dict = {}
    #: True when descriptors are packed binary strings matched by Hamming distance.
    binary: bool = False

    def __init__(self, **conf):
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise InputError(
                f"{type(self).__name__} got unknown option(s) {sorted(unknown)}; "
                f"expected some of {sorted(self.default_conf)}."
            )
        self.conf = {**self.default_conf, **conf}

    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def __call__(self, image: np.ndarray) -> dict[str, np.ndarray]:
        return self.extract(image)


#: Float images may exceed [0, 1] by this much (resampling overshoot); anything beyond is a scaling mistake.
FLOAT_RANGE_TOLERANCE = 1e-3


def check_image(image) -> np.ndarray:
    """The one input check of every extractor: HxW, HxWx1 or HxWx3 (RGB), at least 16x16, uint8, or float with
    finite values in [0, 1]; returns it unchanged, or raises InputError naming what is wrong."""
    if not isinstance(image, np.ndarray):
        raise InputError(f"image must be a numpy array, got {type(image).__name__}.")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3)):
        raise InputError(f"image must be HxW or HxWx3 (RGB), got shape {image.shape}.")
    if image.dtype != np.uint8 and not np.issubdtype(image.dtype, np.floating):
        raise InputError(f"image must be uint8 or float in [0, 1], got dtype {image.dtype}.")
    if min(image.shape[:2]) < 16:
        raise InputError(f"image must be at least 16x16 pixels, got {image.shape[:2]}.")
    if image.dtype != np.uint8:
        if not np.isfinite(image).all():
            raise InputError(f"image contains {np.count_nonzero(~np.isfinite(image))} NaN or infinite value(s).")
        lo, hi = float(image.min()), float(image.max())
        if lo < -FLOAT_RANGE_TOLERANCE or hi > 1 + FLOAT_RANGE_TOLERANCE:
            raise InputError(f"float image must lie in [0, 1], got values in [{lo:.4g}, {hi:.4g}] "
                             f"(divide 8-bit data by 255).")
    return image


def check_longer_side(owner: str, key: str, size) -> None:
    """A resize option (`resize_min` / `resize_max` of the learned extractors) is null or a side in pixels."""
    if size is not None and not (isinstance(size, int | float) and 16 <= size <= 4096):
        raise InputError(f"{owner} {key} must be null or a longer side in pixels (16-4096), got {size!r}.")


def to_float_rgb(image: np.ndarray) -> np.ndarray:
    """HxWx3 float32 RGB in [0, 1] from any accepted input (grey is replicated)."""
    image = check_image(image)
    out = image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else np.clip(image.astype(np.float32), 0, 1)
    if out.ndim == 2:
        out = out[..., None]
    if out.shape[2] == 1:
        out = np.repeat(out, 3, axis=2)
    return out


def to_gray(image: np.ndarray) -> np.ndarray:
    """HxW float32 grey in [0, 1] (ITU-R BT.601 weights 0.299, 0.587, 0.114)."""
    rgb = to_float_rgb(image)
    return rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)


def to_uint8_gray(image: np.ndarray) -> np.ndarray:
    return np.clip(to_gray(image) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def sample_dense(dense: torch.Tensor, keypoints: torch.Tensor, stride: float) -> torch.Tensor:
    """Bilinearly sample a dense map [B, D, h, w] at pixel keypoints [B, N, 2] -> [B, N, D].

    Feature cell i covers pixels [i*s, (i+1)*s), so its centre is at pixel i*s + (s-1)/2, i.e. pixel x maps
    to feature coordinate (x + 0.5) / s - 0.5 with align_corners=False.
    """
    _, _, h, w = dense.shape
    size = keypoints.new_tensor([w * stride, h * stride])
    grid = (keypoints + 0.5) / size * 2.0 - 1.0
    out = F.grid_sample(dense, grid[:, None], mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, :, 0].transpose(1, 2)


def sample_descriptors(dense: torch.Tensor, keypoints: torch.Tensor, stride: float) -> torch.Tensor:
    """`sample_dense` followed by L2 normalization: the descriptors of keypoints [B, N, 2] -> [B, N, D]."""
    return F.normalize(sample_dense(dense, keypoints, stride), dim=-1)


def simple_nms(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """Keep only local maxima within a (2r+1)^2 window: scores [B, H, W] -> same with non-maxima zeroed."""
    if radius <= 0:
        return scores
    # max over a square window is separable: a row pass then a column pass, each as 2r element-wise maxima of
    # shifted views (same result as max_pool2d, several times cheaper on CPU)
    h, w = scores.shape[-2:]
    padded = F.pad(scores, (radius, radius), value=float("-inf"))
    rows = padded[..., :w]
    for i in range(1, 2 * radius + 1):
        rows = torch.maximum(rows, padded[..., i:i + w])
    padded = F.pad(rows, (0, 0, radius, radius), value=float("-inf"))
    pooled = padded[..., :h, :]
    for i in range(1, 2 * radius + 1):
        pooled = torch.maximum(pooled, padded[..., i:i + h, :])
    return torch.where(scores == pooled, scores, torch.zeros_like(scores))


def logits_cell(logits: torch.Tensor) -> int:
    """The cell side of a SuperPoint-layout logit map [B, cell^2+1, h, w]: 8 for 65 channels, 4 for 17."""
    cell = round((logits.shape[1] - 1) ** 0.5)
    if cell * cell + 1 != logits.shape[1]:
        raise ValueError(f"keypoint logits need cell^2 + 1 channels, got {logits.shape[1]}.")
    return cell


def cell_logits_to_heatmap(logits: torch.Tensor, cell: int | None = None) -> torch.Tensor:
    """SuperPoint cell layout: [B, cell^2+1, h, w] logits -> [B, h*cell, w*cell] keypoint probability (the cell
    read off the channel count when None)."""
    cell = cell or logits_cell(logits)
    prob = logits.softmax(dim=1)[:, :-1]
    return F.pixel_shuffle(prob, cell)[:, 0]


def detect_keypoints(
    heatmap: torch.Tensor, nms_radius: int, threshold: float, max_keypoints: int, border: int
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """NMS, border removal, threshold, top-k on a heatmap [B, H, W] -> per image (keypoints [N,2] xy, scores)."""
    heat = simple_nms(heatmap, nms_radius)
    if border > 0:
        heat[:, :border] = 0
        heat[:, -border:] = 0
        heat[:, :, :border] = 0
        heat[:, :, -border:] = 0
    out = []
    for h in heat:
        ys, xs = torch.nonzero(h > threshold, as_tuple=True)
        scores = h[ys, xs]
        if max_keypoints and scores.numel() > max_keypoints:
            scores, idx = scores.topk(max_keypoints)
            ys, xs = ys[idx], xs[idx]
        else:
            scores, idx = scores.sort(descending=True)
            ys, xs = ys[idx], xs[idx]
        out.append((torch.stack([xs, ys], dim=-1).float(), scores))
    return out


def decode_sparse(
    logits: torch.Tensor, dense_descriptors: torch.Tensor, size: tuple[int, int], conf: dict, stride: int = 8,
    reliability: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The one dense-to-sparse decoding of the learned extractors (SuperPoint, XFeat, UWNet), one image:
    cell logits [1, c^2+1, H/c, W/c] and dense descriptors [1, D, H/stride, W/stride] -> keypoints [N, 2] (x, y)
    in the (H, W) input cropped to `size`, scores [N], unit descriptors [N, D]. The keypoint cell c is read off
    the logits (8 for 65 channels; 4 for the finer-cell UWNet's 17), the descriptor map's stride is `stride`.

    `conf` gives nms_radius, detection_threshold, border and max_keypoints, and optionally subpixel_radius
    (`refine_subpixel`; absent or 0 = integer pixels, as the teachers publish them). With
    `reliability` [1, 1, H/stride, W/stride] (XFeat), the top-k is taken after weighting each heatmap score by the
    reliability at the keypoint.
    """
    h, w = size
    heat = cell_logits_to_heatmap(logits)[:, :h, :w].contiguous()
    top_k = 0 if reliability is not None else conf["max_keypoints"]
    (xy, scores), = detect_keypoints(heat, conf["nms_radius"], conf["detection_threshold"], top_k, conf["border"])
    if reliability is not None:
        scores = scores * sample_dense(reliability, xy[None], stride)[0, :, 0]
        order = scores.argsort(descending=True)[: conf["max_keypoints"] or None]
        xy, scores = xy[order], scores[order]
    r = int(conf.get("subpixel_radius") or 0)
    if r > 0:
        xy = refine_subpixel(heat[0], xy, r)
    return xy, scores, sample_descriptors(dense_descriptors, xy[None], stride)[0]


def refine_subpixel(heat: torch.Tensor, xy: torch.Tensor, radius: int) -> torch.Tensor:
    """Keypoints moved to the heat-weighted centre of their (2r+1)^2 window of the heatmap [H, W]. A cell detector
    puts its keypoint on one pixel of a peak that spans several; the centre is what repeats from view to view
    (ALIKED's soft-argmax detector does the same)."""
    if len(xy) == 0:
        return xy
    k = 2 * radius + 1
    padded = F.pad(heat[None, None], (radius,) * 4)[0, 0]
    d = torch.arange(-radius, radius + 1, device=heat.device)
    x, y = xy[:, 0].long(), xy[:, 1].long()
    patch = padded[(y[:, None, None] + radius + d[None, :, None]), (x[:, None, None] + radius + d[None, None, :])]
    patch = patch.reshape(len(xy), k * k)
    w = patch / patch.sum(1, keepdim=True).clamp_min(1e-12)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    off = torch.stack([(w * dx.reshape(1, -1)).sum(1), (w * dy.reshape(1, -1)).sum(1)], 1)
    return xy + off.to(xy.dtype)
