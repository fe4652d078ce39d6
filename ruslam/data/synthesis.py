"""Pseudo-underwater synthesis, paper eq. 4, batched in torch:

    M^c = { L eta^c R^c e^{-beta^c d} } * PSF  +  L eta^c (1 - e^{-beta^c d})  +  W

R is the in-air image (reflectance under white light, max-reflectance prior), A = L_A eta the background light
from `ruslam.data.background_light` (eqs. 5-7), beta from `ruslam.data.water` (Jerlov), d the depth in metres.
`degrade` takes A and a separate low-light factor L in (0, 1] that scales the whole illumination, so the
illumination is L * A; with L = 1, no blur and no noise eq. 4 is exactly eq. 1 with N = A R (eq. 3).

- PSF: linear motion blur (kornia's `get_motion_kernel2d`, uniform weights, reflect border) applied to the
  direct term only. A streak of length l pixels covers 2 floor(l/2) + 1 pixel centres (kornia kernels are odd
  and centred): 11 taps for the paper's 10 px; a streak that rounds to one pixel (l <= 1) means no blur. The
  kernel has few non-zero taps, so it is applied as a sum of shifted copies, the same correlation as
  `kornia.filters.motion_blur` (tested) at a fraction of the cost.
- W: zero-mean Gaussian noise, independent per pixel and channel, std ``noise_std`` (image units, [0, 1]).
- Invalid depth (NaN, +-inf, <= 0): treated as infinitely far, t = 0, so the pixel is pure background light
  L A (plus noise). Kinect/NYU holes are mostly beyond range or on dark/specular surfaces, and "no object
  within range" is what open water shows; a depth map with no valid pixel gives a uniform veil.
- Output clamped to [0, 1].

`PseudoUnderwater` draws the per-image parameters (water type, A from the pool, L, noise std) and the noise
from one `torch.Generator` per image seeded by (seed, index), so an image is the same whatever batch or
DataLoader worker it is drawn in.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import get_motion_kernel2d

from ruslam.data.background_light import background_light_pool
from ruslam.data.water import WATER_TYPES, beta_rgb, check_water_type
from ruslam.errors import InputError


def motion_kernel(angle_deg: float, length: float) -> torch.Tensor | None:
    """kornia's uniform linear motion kernel [k,k] for a streak of ``length`` pixels, or None for no blur."""
    half = int(length // 2)  # the odd tap count nearest l (even l rounds up); round() made 3 px = 5 px
    if half < 1:
        return None
    return get_motion_kernel2d(2 * half + 1, float(angle_deg), 0.0)[0]


def correlate(x: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """2-D correlation of x [B,C,H,W] with a sparse kernel [k,k] under reflect padding (= kornia filter2d)."""
    r = kernel.shape[-1] // 2
    padded = F.pad(x, (r, r, r, r), mode="reflect")
    h, w = x.shape[-2:]
    out = torch.zeros_like(x)
    for i, j in torch.nonzero(kernel).tolist():
        out.add_(padded[..., i:i + h, j:j + w], alpha=float(kernel[i, j]))
    return out


def transmission(depth: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    """t = exp(-beta d) [B,3,H,W]; 0 where the depth is invalid (NaN, inf, <= 0), i.e. infinitely far."""
    valid = torch.isfinite(depth) & (depth > 0)
    far = torch.where(valid, depth, torch.full_like(depth, float("inf")))[:, None]
    rate = beta.clamp(min=1e-12)[:, :, None, None]  # beta = 0 would give 0 * inf = NaN at invalid depth
    return far.mul(-rate).exp_()


def _check(rgb: torch.Tensor, depth: torch.Tensor, **per_image: torch.Tensor) -> None:
    if rgb.ndim != 4 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must be [B,3,H,W]; got {tuple(rgb.shape)}.")
    b, _, h, w = rgb.shape
    if tuple(depth.shape) != (b, h, w):
        raise ValueError(f"depth must be [B,H,W] = {(b, h, w)} to match rgb; got {tuple(depth.shape)}.")
    for name, (value, shape) in per_image.items():
        if tuple(value.shape) != shape:
            raise ValueError(f"{name} must have shape {shape} for a batch of {b}; got {tuple(value.shape)}.")


def _noise(shape, generator, device, dtype) -> torch.Tensor:
    if generator is None or isinstance(generator, torch.Generator):
        gen_device = generator.device if generator is not None else device
        return torch.empty(shape, device=gen_device, dtype=dtype).normal_(generator=generator).to(device)
    if len(generator) != shape[0]:
        raise ValueError(f"Got {len(generator)} generators for a batch of {shape[0]} images.")
    return torch.stack([torch.empty(shape[1:], device=g.device, dtype=dtype).normal_(generator=g).to(device)
                        for g in generator])


def degrade(rgb: torch.Tensor, depth: torch.Tensor, beta: torch.Tensor, A: torch.Tensor, L: torch.Tensor,
            noise_std: torch.Tensor, blur_angle_deg: float | torch.Tensor = 20.0, blur_length: float = 10.0,
            generator: torch.Generator | Sequence[torch.Generator] | None = None) -> torch.Tensor:
    """Eq. 4 on a batch: rgb [B,3,H,W] in [0,1], depth [B,H,W] m, beta [B,3] 1/m, A [B,3], L [B], noise_std [B].

    ``blur_angle_deg`` is one angle or one per image [B]; ``generator`` is one generator for the batch's noise,
    or one per image (so an image's noise does not depend on its batch-mates), or None (torch's global RNG).
    """
    b = rgb.shape[0]
    dev, dt = rgb.device, rgb.dtype
    beta, A, L, noise_std = (torch.as_tensor(v, dtype=dt, device=dev) for v in (beta, A, L, noise_std))
    _check(rgb, depth, beta=(beta, (b, 3)), A=(A, (b, 3)), L=(L, (b,)), noise_std=(noise_std, (b,)))
    t = transmission(depth.to(device=dev, dtype=dt), beta)
    illumination = (L[:, None] * A)[:, :, None, None]  # L * eta of eq. 4 (times the extra low-light factor)
    direct = (rgb * t).mul_(illumination)
    angles = torch.as_tensor(blur_angle_deg, dtype=torch.float32).flatten().tolist()
    if len(angles) not in (1, b):
        raise ValueError(f"blur_angle_deg must be one angle or {b}; got {len(angles)}.")
    if len(set(angles)) == 1:
        kernel = motion_kernel(angles[0], blur_length)
        if kernel is not None:
            direct = correlate(direct, kernel.to(dev, dt))
    else:
        kernels = [motion_kernel(a, blur_length) for a in angles]
        direct = torch.cat([direct[i:i + 1] if k is None else correlate(direct[i:i + 1], k.to(dev, dt))
                            for i, k in enumerate(kernels)])
    out = direct.add_(t.neg_().add_(1).mul_(illumination))  # + L eta (1 - t), reusing t's memory
    if bool((noise_std > 0).any()):
        out.add_(_noise(out.shape, generator, dev, dt).mul_(noise_std[:, None, None, None]))
    return out.clamp_(0.0, 1.0)


def attenuate_eq1(rgb: torch.Tensor, depth: torch.Tensor, beta: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """Eq. 1 (the UWCNN-style model): N t + A (1 - t) with the in-air image N, no PSF, no noise, no L."""
    b = rgb.shape[0]
    beta, A = (torch.as_tensor(v, dtype=rgb.dtype, device=rgb.device) for v in (beta, A))
    _check(rgb, depth, beta=(beta, (b, 3)), A=(A, (b, 3)))
    t = transmission(depth.to(device=rgb.device, dtype=rgb.dtype), beta)
    return (rgb * t).add_((1 - t).mul_(A[:, :, None, None])).clamp_(0.0, 1.0)


def image_generator(seed: int, index: int) -> torch.Generator:
    """The CPU generator of image ``index`` under ``seed`` (SeedSequence mixing, so nearby seeds do not collide)."""
    state = np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint64)[0]
    return torch.Generator().manual_seed(int(state) & ((1 << 63) - 1))


def _range(value, name: str) -> tuple[float, float]:
    lo, hi = (float(value), float(value)) if np.isscalar(value) else (float(value[0]), float(value[1]))
    if not 0 <= lo <= hi:
        raise InputError(f"{name} must be a value or a (lo, hi) range with 0 <= lo <= hi; got {value!r}.")
    return lo, hi


class PseudoUnderwater:
    """Random eq. 4 per image: ``(rgb [B,3,H,W], depth [B,H,W], indices) -> [B,3,H,W]``, seeded by (seed, index).

    Per image: a water type uniformly from ``water_types``, A uniformly from the background-light pool, L
    uniformly in ``low_light``, the noise std uniformly in ``noise_std``. ``background_light`` is None (the
    embedded `default_pool`), a folder of real underwater images (eqs. 5-7 with N=10, P=8), or an array [K,3].
    Fixed water: ``PseudoUnderwater(...).for_water_type("III")`` or ``water_types=["III"]``.
    """

    def __init__(self, water_types: Sequence[str] = WATER_TYPES, background_light=None,
                 blur_angle_deg: float = 20.0, blur_length: float = 10.0, noise_std=(0.005, 0.02),
                 low_light=(0.7, 1.0), seed: int = 0):
        if isinstance(water_types, str):
            water_types = [water_types]
        self.water_types = tuple(check_water_type(str(w)) for w in water_types)
        if not self.water_types:
            raise InputError(f"water_types is empty; expected some of {', '.join(WATER_TYPES)}.")
        if background_light is None or isinstance(background_light, str | Path):
            pool = background_light_pool(background_light)
        else:
            pool = np.asarray(background_light, dtype=np.float64)
        if pool.ndim != 2 or pool.shape[1] != 3 or len(pool) == 0 or not np.all((pool >= 0) & (pool <= 1)):
            raise InputError(f"background_light pool must be a non-empty [K,3] array in [0,1]; got {pool.shape}.")
        self.pool = pool
        self.betas = np.stack([beta_rgb(w) for w in self.water_types])
        self.blur_angle_deg, self.blur_length = float(blur_angle_deg), float(blur_length)
        self.noise_std, self.low_light = _range(noise_std, "noise_std"), _range(low_light, "low_light")
        if self.low_light[1] > 1:
            raise InputError(f"low_light must lie in [0, 1]; got {low_light!r}.")
        self.seed = int(seed)

    def for_water_type(self, name: str) -> PseudoUnderwater:
        """The same synthesis with the water fixed to Jerlov type ``name``."""
        return PseudoUnderwater([name], self.pool, self.blur_angle_deg, self.blur_length, self.noise_std,
                                self.low_light, self.seed)

    def draw(self, generator: torch.Generator) -> dict:
        """The per-image parameters, drawn from ``generator`` (first the water, then A, L, noise std)."""
        u = torch.rand(4, generator=generator, dtype=torch.float64).tolist()
        w = min(int(u[0] * len(self.water_types)), len(self.water_types) - 1)
        k = min(int(u[1] * len(self.pool)), len(self.pool) - 1)
        return {"water_type": self.water_types[w], "beta": self.betas[w], "A": self.pool[k],
                "L": self.low_light[0] + u[2] * (self.low_light[1] - self.low_light[0]),
                "noise_std": self.noise_std[0] + u[3] * (self.noise_std[1] - self.noise_std[0])}

    def params(self, index: int) -> dict:
        """The parameters image ``index`` gets (for reports and debugging)."""
        return self.draw(image_generator(self.seed, index))

    def __call__(self, rgb: torch.Tensor, depth: torch.Tensor, indices: Sequence[int]) -> torch.Tensor:
        indices = [int(i) for i in indices]
        if len(indices) != rgb.shape[0]:
            raise ValueError(f"Got {len(indices)} indices for a batch of {rgb.shape[0]} images.")
        generators = [image_generator(self.seed, i) for i in indices]
        drawn = [self.draw(g) for g in generators]
        stack = {key: torch.as_tensor(np.array([d[key] for d in drawn]), dtype=rgb.dtype, device=rgb.device)
                 for key in ("beta", "A", "L", "noise_std")}
        return degrade(rgb, depth, stack["beta"], stack["A"], stack["L"], stack["noise_std"],
                       self.blur_angle_deg, self.blur_length, generator=generators)

    def __repr__(self) -> str:
        return (f"PseudoUnderwater(water_types={list(self.water_types)}, pool={len(self.pool)} entries, "
                f"blur={self.blur_angle_deg}deg/{self.blur_length}px, noise_std={self.noise_std}, "
                f"low_light={self.low_light}, seed={self.seed})")
