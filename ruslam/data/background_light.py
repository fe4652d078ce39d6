"""Background light A (eqs. 5-7): a pool A* of RGB triples that each synthesized image draws one entry from.

From real underwater images (the paper's recipe): P random 8x8 regions Omega_i in each of N images; per region
V^c = max_{x in Omega_i} M^c(x) (eq. 5, max-reflectance prior: the brightest pixel of a region shows the
illumination), L = max_c V^c (eq. 7), eta^c = V^c / L (eq. 6) and A = L * eta. The pool has N * P entries.

Embedded default (a fresh clone has no underwater photographs): `default_pool`, the colour of the daylight that
reaches depth z in each Jerlov water type, as an sRGB camera white-balanced at the surface records it:

    rgb_c(z) = sum_lambda S_c D65 exp(-Kd z) / sum_lambda S_c D65,   eta = rgb / max(rgb),   A = L * eta,

with S_c D65 and Kd as in `ruslam.data.water` (jerlov), depths 2, 5 and 10 m (where a camera still sees in
turbid coastal water) and L = 0.7. Ambient light at depth is what the water leaves of daylight, so this gives
the blue of clear ocean, the green of coastal water and the yellow-green of turbid 9C without a hand-typed
colour. It ignores the spectral shape of the scattering that turns this light towards the camera (bb/c), which
in clear water makes the real veil bluer still. L = 0.7: auto-exposure puts the open-water background high in
the range; eqs. 5-7 on 23 EUVP test samples (8 regions each, seed 0) give a median region L of
0.70.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ruslam.data.water import WATER_TYPES, camera_response, kd_spectrum
from ruslam.errors import InputError, MissingInput

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
DEFAULT_DEPTHS_M = (2.0, 5.0, 10.0)
DEFAULT_L = 0.7


def region_light(region: np.ndarray) -> tuple[float, np.ndarray]:
    """(L, eta) of one region [h,w,3] in [0,1]: eqs. 5-7. A black region has L = 0 and eta = 0."""
    V = region.reshape(-1, 3).max(axis=0).astype(np.float64)  # eq. 5
    L = float(V.max())  # eq. 7
    eta = V / L if L > 0 else np.zeros(3)  # eq. 6
    return L, eta


def regions_background_light(image: np.ndarray, num_regions: int, rng: np.random.Generator,
                             region_size: int = 8) -> np.ndarray:
    """A = L * eta [num_regions, 3] from ``num_regions`` uniformly placed region_size^2 windows of ``image``."""
    h, w = image.shape[:2]
    if h < region_size or w < region_size:
        raise InputError(f"Image of {h}x{w} pixels is smaller than one {region_size}x{region_size} region.")
    ys = rng.integers(0, h - region_size + 1, size=num_regions)
    xs = rng.integers(0, w - region_size + 1, size=num_regions)
    out = np.empty((num_regions, 3))
    for k, (y, x) in enumerate(zip(ys, xs, strict=True)):
        L, eta = region_light(image[y:y + region_size, x:x + region_size])
        out[k] = L * eta
    return out


def read_rgb(path: Path) -> np.ndarray:
    """float64 RGB [h,w,3] in [0,1] from an 8- or 16-bit colour image; one clear sentence otherwise."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"Cannot read {path} as an image (corrupt or unsupported format).")
    if raw.ndim == 2 or raw.shape[2] == 1:
        raise InputError(f"{path} is a grayscale image; background light needs colour (RGB) underwater images.")
    if raw.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{path} has {raw.dtype} pixels; expected an 8- or 16-bit RGB image.")
    scale = 255.0 if raw.dtype == np.uint8 else 65535.0
    return raw[..., 2::-1].astype(np.float64) / scale  # BGR(A) -> RGB


def list_images(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise MissingInput(f"Underwater image folder {folder} does not exist.")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def estimate_pool(folder: str | Path, num_images: int = 10, regions_per_image: int = 8, region_size: int = 8,
                  seed: int = 0) -> np.ndarray:
    """The pool A* [N*P, 3] from N images of ``folder`` (a seeded choice when it holds more), P regions each."""
    if num_images < 1 or regions_per_image < 1:
        raise InputError(f"num_images ({num_images}) and regions_per_image ({regions_per_image}) must be >= 1.")
    paths = list_images(folder)
    if len(paths) < num_images:
        raise InputError(f"{folder} holds {len(paths)} images ({', '.join(IMAGE_SUFFIXES)}); "
                         f"background-light estimation needs N = {num_images}.")
    rng = np.random.default_rng(seed)
    chosen = [paths[i] for i in sorted(rng.choice(len(paths), size=num_images, replace=False))]
    return np.concatenate([regions_background_light(read_rgb(p), regions_per_image, rng, region_size)
                           for p in chosen])


def ambient_rgb(water_type: str, depth_m: float) -> np.ndarray:
    """Surface-white-balanced camera RGB [3] of daylight after ``depth_m`` metres of ``water_type``."""
    _, weights = camera_response()
    transmitted = np.exp(-kd_spectrum(water_type) * depth_m)
    return (weights * transmitted[:, None]).sum(0) / weights.sum(0)


def default_pool(water_types=WATER_TYPES, depths_m=DEFAULT_DEPTHS_M, L: float = DEFAULT_L) -> np.ndarray:
    """Embedded pool [len(water_types)*len(depths), 3]: A = L * eta with eta the ambient colour (module doc)."""
    rows = []
    for name in water_types:
        for z in depths_m:
            rgb = ambient_rgb(name, z)
            rows.append(L * rgb / rgb.max())
    return np.asarray(rows)


def background_light_pool(folder: str | Path | None = None, **kwargs) -> np.ndarray:
    """`estimate_pool(folder, **kwargs)` when a folder is given, else the embedded `default_pool()`."""
    if folder is None or str(folder) == "":
        return default_pool()
    return estimate_pool(folder, **kwargs)
