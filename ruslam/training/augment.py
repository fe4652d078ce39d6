"""Augmentations of one distillation sample: photometric on the student input, geometric on input AND targets.

Geometric (beyond the paper): XFeat/SuperPoint targets are not rotation-invariant, but the
student can be. The student sees the image warped by a random homography (in-plane rotation up to 180 degrees,
scale, mild perspective); the teacher's dense target maps, computed once on the unwarped clean image, are warped
spatially by the same homography with their *values unchanged*, so the student must give the same descriptor
whatever the rotation. Cells that the warp brings in from outside the image are masked out of the loss.

Coordinates: pixel centres at integer coordinates; a 1/8 cell u covers pixels [8u, 8u+8) so its centre is pixel
8u + 3.5 (the project's sampling convention, `ruslam.models.extractor.sample_dense`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.geometry.transform import warp_perspective

CELL = 8


def seeded_generator(*keys: int) -> torch.Generator:
    """A generator seeded by a tuple of ints (e.g. seed, epoch, index) so every sample is reproducible."""
    value = 0
    for k in keys:
        value = (value * 1_000_003 + int(k)) % (2**63 - 1)
    return torch.Generator().manual_seed(value)


def _uniform(gen: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * torch.rand((), generator=gen).item()


class GeometricAugment:
    """Random homography about the image centre; with probability ``rotation_prob`` the rotation is drawn from
    [-max_rotation_deg, max_rotation_deg], otherwise it stays within +-``small_rotation_deg`` (so upright
    images keep being seen as the teacher sees them)."""

    def __init__(self, max_rotation_deg: float = 180.0, rotation_prob: float = 0.75, small_rotation_deg: float = 10.0,
                 scale: tuple[float, float] = (0.8, 1.25), perspective: float = 0.1):
        self.max_rotation_deg = max_rotation_deg
        self.rotation_prob = rotation_prob
        self.small_rotation_deg = small_rotation_deg
        self.scale = tuple(scale)
        self.perspective = perspective

    def sample(self, height: int, width: int, gen: torch.Generator) -> torch.Tensor:
        """3x3 homography (float64) mapping input pixels to warped pixels."""
        big = torch.rand((), generator=gen).item() < self.rotation_prob
        limit = self.max_rotation_deg if big else self.small_rotation_deg
        angle = math.radians(_uniform(gen, -limit, limit))
        s = math.exp(_uniform(gen, math.log(self.scale[0]), math.log(self.scale[1])))
        # Perspective terms sized so a corner's homogeneous scale changes by at most +-perspective.
        px = _uniform(gen, -self.perspective, self.perspective) / (width / 2)
        py = _uniform(gen, -self.perspective, self.perspective) / (height / 2)
        cx, cy = (width - 1) / 2, (height - 1) / 2
        to_centre = torch.tensor([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]], dtype=torch.float64)
        back = torch.tensor([[1, 0, cx], [0, 1, cy], [0, 0, 1]], dtype=torch.float64)
        c, sn = math.cos(angle) * s, math.sin(angle) * s
        rot = torch.tensor([[c, -sn, 0], [sn, c, 0], [0, 0, 1]], dtype=torch.float64)
        persp = torch.tensor([[1, 0, 0], [0, 1, 0], [px, py, 1]], dtype=torch.float64)
        return back @ persp @ rot @ to_centre


def _warp(x: torch.Tensor, homography: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return warp_perspective(x[None], homography[None].to(device=x.device, dtype=x.dtype), size, mode="bilinear",
                            padding_mode="zeros", align_corners=True)[0]


def cell_homography(homography: torch.Tensor) -> torch.Tensor:
    """The pixel homography expressed on the 1/8 cell grid: S^-1 H S with S(u) = 8u + 3.5."""
    s = torch.tensor([[CELL, 0, (CELL - 1) / 2], [0, CELL, (CELL - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    return torch.linalg.inv(s) @ homography.double() @ s


def warp_image(image: torch.Tensor, homography: torch.Tensor) -> torch.Tensor:
    """[C, H, W] -> the same image seen through the homography (zeros outside)."""
    return _warp(image, homography, tuple(image.shape[-2:]))


def warp_targets(targets: dict[str, torch.Tensor], homography: torch.Tensor) -> dict[str, torch.Tensor]:
    """Warp teacher maps at 1/8 by a pixel homography; adds ``mask`` [h, w] (1 = cell fully inside the image).

    Keypoint cell distributions are warped as full-resolution maps: the 64 in-cell probabilities as a heatmap,
    the dustbin as a per-pixel constant of its cell; both are re-binned into cells and renormalized, and stored
    back as log-probabilities (the loss applies softmax to target logits).
    """
    logits = targets["keypoint_logits"].float()
    _, h, w = logits.shape
    size = (h * CELL, w * CELL)
    prob = logits.softmax(0)
    heat = F.pixel_shuffle(prob[None, :-1], CELL)[0]  # [1, H, W]
    dust = F.interpolate(prob[None, -1:], scale_factor=CELL, mode="nearest")[0]  # [1, H, W]
    warped = _warp(torch.cat([heat, dust, torch.ones_like(heat)]), homography, size)
    cells = F.pixel_unshuffle(warped[:1][None], CELL)[0]  # [64, h, w]
    dust_c = F.avg_pool2d(warped[1:2][None], CELL)[0]
    inside = -F.max_pool2d(-warped[2:3][None], CELL)[0, 0]  # min over the cell
    mask = (inside > 0.999).float()
    new_prob = torch.cat([cells, dust_c]).clamp_min(0)
    new_prob = new_prob / new_prob.sum(0, keepdim=True).clamp_min(1e-6)
    # Outside cells: a pure dustbin (masked anyway), so the target stays a valid distribution.
    dustbin_only = torch.zeros_like(new_prob)
    dustbin_only[-1] = 1.0
    new_prob = torch.where(mask > 0, new_prob, dustbin_only)
    out = dict(targets)
    out["keypoint_logits"] = new_prob.clamp_min(1e-8).log()
    desc = _warp(targets["dense_descriptors"].float(), cell_homography(homography), (h, w))
    out["dense_descriptors"] = F.normalize(desc, dim=0)
    out["mask"] = mask
    return out


def warp_targets_batch(targets: dict[str, torch.Tensor], homographies: torch.Tensor) -> dict[str, torch.Tensor]:
    """`warp_targets` for a batch: maps [B, ...] and pixel homographies [B, 3, 3], one warp call per map kind (the
    online trainer's GPU path makes its views this way); ``mask`` is [B, h, w]."""
    logits = targets["keypoint_logits"].float()
    b, _, h, w = logits.shape
    size = (h * CELL, w * CELL)
    prob = logits.softmax(1)
    heat = F.pixel_shuffle(prob[:, :-1], CELL)  # [B, 1, H, W]
    dust = F.interpolate(prob[:, -1:], scale_factor=CELL, mode="nearest")
    stack = torch.cat([heat, dust, torch.ones_like(heat)], 1)
    warped = warp_perspective(stack, homographies.to(device=stack.device, dtype=stack.dtype), size, mode="bilinear",
                              padding_mode="zeros", align_corners=True)
    cells = F.pixel_unshuffle(warped[:, :1], CELL)
    dust_c = F.avg_pool2d(warped[:, 1:2], CELL)
    inside = -F.max_pool2d(-warped[:, 2:3], CELL)[:, 0]
    mask = (inside > 0.999).float()
    new_prob = torch.cat([cells, dust_c], 1).clamp_min(0)
    new_prob = new_prob / new_prob.sum(1, keepdim=True).clamp_min(1e-6)
    dustbin_only = torch.zeros_like(new_prob)
    dustbin_only[:, -1] = 1.0
    new_prob = torch.where(mask[:, None] > 0, new_prob, dustbin_only)
    out = dict(targets)
    out["keypoint_logits"] = new_prob.clamp_min(1e-8).log()
    cells_h = torch.stack([cell_homography(hom.cpu()) for hom in homographies])
    desc = targets["dense_descriptors"].float()
    desc = warp_perspective(desc, cells_h.to(device=desc.device, dtype=desc.dtype), (h, w), mode="bilinear",
                            padding_mode="zeros", align_corners=True)
    out["dense_descriptors"] = F.normalize(desc, dim=1)
    out["mask"] = mask
    return out


class PhotometricAugment:
    """Brightness, contrast, gamma and Gaussian noise on the student input only (the teacher saw the clean one)."""

    def __init__(self, brightness: float = 0.15, contrast: float = 0.25, gamma: float = 0.25, noise_std: float = 0.02):
        self.brightness, self.contrast, self.gamma, self.noise_std = brightness, contrast, gamma, noise_std

    def __call__(self, image: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        b = _uniform(gen, -self.brightness, self.brightness)
        c = math.exp(_uniform(gen, -self.contrast, self.contrast))
        g = math.exp(_uniform(gen, -self.gamma, self.gamma))
        mean = image.mean()
        out = ((image - mean) * c + mean + b).clamp(0, 1) ** g
        if self.noise_std > 0:
            out = out + _uniform(gen, 0, self.noise_std) * torch.randn(image.shape, generator=gen)
        return out.clamp(0, 1)
