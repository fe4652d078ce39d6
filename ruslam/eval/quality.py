"""Reference-free underwater image quality: UCIQE (Yang & Sowmya 2015) and UIQM (Panetta, Gao & Agaian 2016).

Implemented from the papers' definitions, with the choices they leave open stated here (docs/design.md).
Every function takes an RGB image [H,W,3], uint8 or float in [0,1]; UIQM terms work on 0-255 intensities as
the paper's constants expect (float arithmetic: no uint8 wrap-around of R - G, no integer division).

UIQM = 0.0282 UICM + 0.2953 UISM + 3.5753 UIConM.

- UICM: RG = R - G, YB = (R + G)/2 - B. Asymmetric alpha-trimmed mean with alpha_L = alpha_R = 0.1
  (drop the ceil(0.1 K) smallest and floor(0.1 K) largest of the K values), variance = mean squared deviation of
  all K values from that mean. UICM = -0.0268 sqrt(mu_RG^2 + mu_YB^2) + 0.1586 sqrt(var_RG + var_YB).
- UISM = sum_c lambda_c EME(Sobel_c * c), lambda = 0.299, 0.587, 0.114 (the luma weights; public copies carry
  0.144). Sobel_c: gradient magnitude of channel c (3x3 Sobel, replicated border). EME over 8x8 blocks:
  (2 / (k1 k2)) sum ln(I_max / I_min); a block whose minimum is 0 contributes 0 (the ratio is undefined).
- UIConM = logAMEE of the intensity (luma 0.299 R + 0.587 G + 0.114 B) over 8x8 blocks, in PLIP arithmetic
  (gamma = k = 1026): r = (I_max (-) I_min) / (I_max (+) I_min) with a (+) b = a + b - ab/gamma and
  a (-) b = k (a - b) / (k - b); block term h = -r ln r (the entropy form, >= 0: the printed r ln r is <= 0
  for r <= 1 and would make the best-contrast image score lowest); blocks are summed with (+) and scaled by
  (1/(k1 k2)) (x), i.e. UIConM = gamma (1 - prod_blocks (1 - h/gamma)^(1/(k1 k2))), a PLIP mean of h.
  -r ln r rises with contrast up to r = 1/e; natural image blocks lie well below it.
- Blocks: the image is cropped to whole 8x8 blocks from the top-left; UIQM therefore depends on image size,
  so compare methods at one resolution.

UCIQE = 0.4680 sigma_c + 0.2745 con_l + 0.2576 mu_s in CIELab (OpenCV, D65): L and chroma C = sqrt(a^2 + b^2)
divided by 100 (L to [0,1]); sigma_c = std of C; con_l = 99th minus 1st percentile of L; mu_s = mean of the
saturation C / L (0 where L = 0).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

UIQM_WEIGHTS = (0.0282, 0.2953, 3.5753)
UISM_WEIGHTS = (0.299, 0.587, 0.114)
UCIQE_WEIGHTS = (0.4680, 0.2745, 0.2576)
PLIP_GAMMA = PLIP_K = 1026.0
BLOCK = 8


def as_rgb255(image: np.ndarray) -> np.ndarray:
    """float64 [H,W,3] in 0..255 from uint8 or float-in-[0,1] RGB; one clear sentence otherwise."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"Expected an RGB image [H,W,3]; got shape {image.shape}.")
    if image.dtype == np.uint8:
        return image.astype(np.float64)
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"Expected uint8 or float RGB in [0,1]; got {image.dtype} pixels.")
    return np.clip(image.astype(np.float64), 0.0, 1.0) * 255.0


def alpha_trimmed_mean_var(values: np.ndarray, alpha_l: float = 0.1, alpha_r: float = 0.1) -> tuple[float, float]:
    """Asymmetric alpha-trimmed mean and the mean squared deviation of all values from it (UICM)."""
    x = np.asarray(values, dtype=np.float64).ravel()
    k = x.size
    lo, hi = math.ceil(alpha_l * k), math.floor(alpha_r * k)
    kept = np.partition(x, [lo, k - hi - 1])[lo:k - hi] if k - hi - 1 > lo else np.sort(x)[lo:k - hi]
    mu = float(kept.mean())
    return mu, float(np.mean((x - mu) ** 2))


def uicm(image: np.ndarray) -> float:
    x = as_rgb255(image)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    mu_rg, var_rg = alpha_trimmed_mean_var(r - g)
    mu_yb, var_yb = alpha_trimmed_mean_var((r + g) / 2 - b)
    return -0.0268 * math.hypot(mu_rg, mu_yb) + 0.1586 * math.sqrt(var_rg + var_yb)


def blocks(channel: np.ndarray, size: int = BLOCK) -> np.ndarray:
    """[k1, k2, size*size] view of the whole size x size blocks of a 2-D array (top-left crop)."""
    k1, k2 = channel.shape[0] // size, channel.shape[1] // size
    if k1 == 0 or k2 == 0:
        raise ValueError(f"Image of {channel.shape[0]}x{channel.shape[1]} is smaller than one {size}x{size} block.")
    c = channel[:k1 * size, :k2 * size].reshape(k1, size, k2, size).transpose(0, 2, 1, 3)
    return c.reshape(k1, k2, size * size)


def eme(channel: np.ndarray, size: int = BLOCK) -> float:
    """(2 / (k1 k2)) sum ln(max / min) over blocks; blocks with min 0 contribute 0."""
    bl = blocks(channel, size)
    hi, lo = bl.max(-1), bl.min(-1)
    ok = lo > 0
    return 2.0 * float(np.log(hi[ok] / lo[ok]).sum()) / hi.size


def sobel_magnitude(channel: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(channel, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(channel, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(gx * gx + gy * gy)


def uism(image: np.ndarray) -> float:
    x = as_rgb255(image)
    return float(sum(w * eme(sobel_magnitude(x[..., c]) * x[..., c]) for c, w in enumerate(UISM_WEIGHTS)))


def plip_add(a, b):
    return a + b - a * b / PLIP_GAMMA


def plip_sub(a, b):
    return PLIP_K * (a - b) / (PLIP_K - b)


def uiconm(image: np.ndarray) -> float:
    x = as_rgb255(image)
    intensity = x @ np.asarray(UISM_WEIGHTS)
    bl = blocks(intensity)
    hi, lo = bl.max(-1), bl.min(-1)
    num, den = plip_sub(hi, lo), plip_add(hi, lo)
    r = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    h = np.where(r > 0, -r * np.log(np.where(r > 0, r, 1.0)), 0.0)
    return float(PLIP_GAMMA * (1.0 - np.exp(np.mean(np.log1p(-h / PLIP_GAMMA)))))


def uiqm_terms(image: np.ndarray) -> dict[str, float]:
    """{"uiqm", "uicm", "uism", "uiconm"} of one image."""
    terms = {"uicm": uicm(image), "uism": uism(image), "uiconm": uiconm(image)}
    c1, c2, c3 = UIQM_WEIGHTS
    return {"uiqm": c1 * terms["uicm"] + c2 * terms["uism"] + c3 * terms["uiconm"], **terms}


def uciqe(image: np.ndarray) -> float:
    rgb = (as_rgb255(image) / 255.0).astype(np.float32)
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab).astype(np.float64)
    lum = lab[..., 0] / 100.0
    chroma = np.hypot(lab[..., 1], lab[..., 2]) / 100.0
    sigma_c = float(chroma.std())
    con_l = float(np.percentile(lum, 99) - np.percentile(lum, 1))
    saturation = np.divide(chroma, lum, out=np.zeros_like(chroma), where=lum > 0)
    c1, c2, c3 = UCIQE_WEIGHTS
    return c1 * sigma_c + c2 * con_l + c3 * float(saturation.mean())


def quality(image: np.ndarray) -> dict[str, float]:
    """All Table 1 figures of one image: uciqe, uiqm, uicm, uism, uiconm."""
    return {"uciqe": uciqe(image), **uiqm_terms(image)}
