"""Texture bank of the procedural RGB-D scenes: periodic images rich in corners and blobs, with mip levels.

Keypoint learning needs surfaces that give many *repeatable* corners and blobs, so the procedural textures are
made of sharp-edged shapes, checkers, bricks, Voronoi cells, posterized noise and plaids, all periodic (they tile
without seams).  Images that matplotlib ships in ``mpl-data/sample_data`` (a photograph, a logo, a hill-shaded
elevation model) add natural content when present; the bank is fully procedural otherwise.  Mip levels let the
renderer pick a texture resolution matching the pixel footprint, which avoids aliasing (aliased texture gives
corners that flicker between nearby views and are not repeatable).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

TEXTURE_SIZE = 256
_SHIFTS = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]


def _colour(rng: np.random.Generator) -> tuple[int, int, int]:
    hsv = np.array([[[rng.integers(0, 180), rng.integers(20, 200), rng.integers(50, 256)]]], np.uint8)
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0])


def _periodic_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth periodic value noise in [0, 1]: a random grid upsampled with its wrapped neighbours."""
    grid = rng.random((cells, cells)).astype(np.float32)
    big = cv2.resize(np.tile(grid, (3, 3)), (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
    out = big[size:2 * size, size:2 * size]
    return (out - out.min()) / max(float(out.max() - out.min()), 1e-6)


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, count: int, max_size: float) -> None:
    """Random filled rectangles, ellipses and polygons, drawn wrapped so the texture stays periodic."""
    s = img.shape[0]
    for _ in range(count):
        colour, kind = _colour(rng), rng.integers(0, 4)
        cx, cy = rng.uniform(0, s, 2)
        a, b = rng.uniform(0.15, 1.0, 2) * max_size
        angle = rng.uniform(0, 180)
        if kind == 0:
            pts = cv2.boxPoints(((cx, cy), (a, b), angle))
        elif kind == 1:
            pts = None
        else:
            n = 3 if kind == 2 else int(rng.integers(5, 9))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = rng.uniform(0.4, 1.0, n) * a / 2 * (1 if kind == 2 else 1.3)
            pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1)
        for dx, dy in _SHIFTS:
            if pts is None:
                cv2.ellipse(img, (int(cx + dx * s), int(cy + dy * s)), (int(a / 2), int(b / 2)), angle, 0, 360,
                            colour, -1, cv2.LINE_AA)
            else:
                shifted = (pts + np.array([dx * s, dy * s])).round().astype(np.int32)
                cv2.fillPoly(img, [shifted], colour, cv2.LINE_AA)


def shapes_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    img = np.empty((size, size, 3), np.uint8)
    img[:] = _colour(rng)
    _draw_shapes(img, rng, int(rng.integers(60, 120)), size / 5)
    return img


def checker_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    n = int(rng.choice([8, 16]))
    yy, xx = np.mgrid[0:size, 0:size] * n // size
    c0, c1 = np.array(_colour(rng), np.uint8), np.array(_colour(rng), np.uint8)
    img = np.where(((xx + yy) % 2 == 0)[..., None], c0, c1).astype(np.uint8)
    _draw_shapes(img, rng, int(rng.integers(20, 50)), size / 8)  # break the symmetry: corners become distinctive
    return img


def bricks_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    rows, cols = int(rng.choice([4, 8, 16])), int(rng.choice([2, 4, 8]))
    bh, bw = size // rows, size // cols
    mortar = np.array(_colour(rng), np.uint8)
    base = np.array(_colour(rng), np.float32)
    img = np.empty((size, size, 3), np.uint8)
    img[:] = mortar
    gap = max(2, bh // 8)
    for r in range(rows):
        shift = (bw // 2) * (r % 2)
        for c in range(cols + 1):
            colour = np.clip(base * rng.uniform(0.6, 1.3), 0, 255).astype(np.uint8).tolist()
            x0 = c * bw - shift
            for dx in (-size, 0, size):
                cv2.rectangle(img, (x0 + dx + gap, r * bh + gap), (x0 + dx + bw - gap, r * bh + bh - gap), colour, -1)
    _draw_shapes(img, rng, int(rng.integers(10, 25)), size / 10)
    return img


def cells_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """Periodic Voronoi cells with dark borders: polygon junctions are natural corners."""
    n = int(rng.integers(20, 60))
    seeds = rng.integers(0, size, (n, 2))
    canvas = np.ones((3 * size, 3 * size), np.uint8)
    for dx, dy in _SHIFTS:  # seeds tiled 3x3: the centre tile sees its wrapped neighbours
        canvas[seeds[:, 1] + (dy + 1) * size, seeds[:, 0] + (dx + 1) * size] = 0
    _, labels = cv2.distanceTransformWithLabels(canvas, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    seed_of_label = np.zeros(labels.max() + 1, np.int64)
    for dx, dy in _SHIFTS:
        seed_of_label[labels[seeds[:, 1] + (dy + 1) * size, seeds[:, 0] + (dx + 1) * size]] = np.arange(n)
    cell = seed_of_label[labels[size - 1:2 * size + 1, size - 1:2 * size + 1]]
    border = (cell[1:-1, 1:-1] != cell[1:-1, 2:]) | (cell[1:-1, 1:-1] != cell[2:, 1:-1])
    border = cv2.dilate(border.astype(np.uint8), np.ones((2, 2), np.uint8)) > 0
    palette = np.array([_colour(rng) for _ in range(n)], np.uint8)
    img = palette[cell[1:-1, 1:-1]]
    img[border] = (np.array(_colour(rng)) * 0.3).astype(np.uint8)
    return img


def blobs_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """Posterized fractal noise through a colormap: blobs with crisp, irregular outlines."""
    import matplotlib  # noqa: PLC0415 (only needed when the bank is built)

    noise = sum(_periodic_noise(rng, size, c) / (i + 1) for i, c in enumerate((4, 8, 16)))
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    levels = int(rng.integers(4, 8))
    posterized = np.floor(noise * levels) / (levels - 1)
    names = ["viridis", "copper", "tab20", "Set3", "plasma", "coolwarm", "twilight"]
    cmap = matplotlib.colormaps[str(rng.choice(names))]
    img = np.ascontiguousarray((cmap(np.clip(posterized, 0, 1))[..., :3] * 255).astype(np.uint8))
    _draw_shapes(img, rng, int(rng.integers(15, 40)), size / 8)
    return img


def plaid_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size] / size
    img = np.zeros((size, size, 3), np.float32)
    for _ in range(2):
        kx, ky = rng.integers(-6, 7, 2)
        kx = kx if kx or ky else 3
        wave = (np.sin(2 * np.pi * (kx * xx + ky * yy) + rng.uniform(0, 6.3)) > rng.uniform(-0.5, 0.5))
        img += wave[..., None] * np.array(_colour(rng), np.float32) * 0.6
    img = np.clip(img + np.array(_colour(rng), np.float32) * 0.3, 0, 255).astype(np.uint8)
    _draw_shapes(img, rng, int(rng.integers(15, 40)), size / 8)
    return img


PROCEDURAL_KINDS = (shapes_texture, checker_texture, bricks_texture, cells_texture, blobs_texture, plaid_texture)


def _sample_path(name: str):
    from matplotlib import cbook  # noqa: PLC0415

    try:
        return cbook.get_sample_data(name, asfileobj=False)
    except (FileNotFoundError, ValueError):
        return None


def shipped_textures(size: int = TEXTURE_SIZE) -> list[np.ndarray]:
    """Textures from images matplotlib ships (empty list when its sample data is not installed)."""
    out = []
    path = _sample_path("grace_hopper.jpg")
    img = None if path is None else cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is not None:
        side = min(img.shape[:2])
        out.append(cv2.resize(img[:side, :side, ::-1], (size, size), interpolation=cv2.INTER_AREA))
    path = _sample_path("jacksboro_fault_dem.npz")
    if path is not None:
        import matplotlib  # noqa: PLC0415
        from matplotlib.colors import LightSource  # noqa: PLC0415

        elevation = np.load(path)["elevation"].astype(np.float64)
        shaded = LightSource(azdeg=315, altdeg=35).shade(elevation, cmap=matplotlib.colormaps["gist_earth"],
                                                         vert_exag=0.05, blend_mode="overlay")
        side = min(elevation.shape)
        out.append(cv2.resize((shaded[:side, :side, :3] * 255).astype(np.uint8), (size, size),
                              interpolation=cv2.INTER_AREA))
    for name in ("Minduka_Present_Blue_Pack.png", "logo2.png"):
        path = _sample_path(name)
        rgba = None if path is None else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if rgba is None or rgba.ndim != 3 or rgba.shape[2] != 4:
            continue
        rgba = rgba[..., [2, 1, 0, 3]].astype(np.float32) / 255.0
        scale = size / 2 / max(rgba.shape[:2])
        rgba = cv2.resize(rgba, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        canvas = np.full((size, size, 3), 0.85, np.float32)
        h, w = rgba.shape[:2]
        for y0 in (0, size // 2):
            for x0 in (0, size // 2):
                patch = canvas[y0:y0 + h, x0:x0 + w]
                patch[:] = rgba[..., :3] * rgba[..., 3:] + patch * (1 - rgba[..., 3:])
        out.append((canvas * 255).astype(np.uint8))
    return out


@lru_cache(maxsize=4)
def texture_bank(seed: int, count: int = 48, size: int = TEXTURE_SIZE) -> tuple[np.ndarray, ...]:
    """Mip levels of a deterministic bank of ``count`` RGB uint8 textures: level l is [count, size/2^l, ...,3].

    Cached per process, so every dataset with the same seed shares one bank (a DataLoader worker builds its own).
    """
    if size < 8 or size & (size - 1):
        raise ValueError(f"Texture size must be a power of two >= 8 (wrapping uses a bit mask), got {size}.")
    rng = np.random.default_rng([seed, 7919])
    bank = shipped_textures(size)[:count]
    while len(bank) < count:
        bank.append(PROCEDURAL_KINDS[len(bank) % len(PROCEDURAL_KINDS)](rng, size))
    levels = [np.stack(bank)]
    while levels[-1].shape[1] > 4:
        s = levels[-1].shape[1] // 2
        levels.append(np.stack([cv2.resize(t, (s, s), interpolation=cv2.INTER_AREA) for t in levels[-1]]))
    for level in levels:
        level.setflags(write=False)
    return tuple(levels)


def sample_textures(levels: tuple[np.ndarray, ...], tex: np.ndarray, x: np.ndarray, y: np.ndarray,
                    footprint: np.ndarray) -> np.ndarray:
    """Bilinear, wrapped lookup of texel coordinates (x, y) at level 0 in textures ``tex`` -> [N, 3] in [0, 1].

    ``footprint`` (level-0 texels per pixel) picks the mip level, so minified textures are pre-filtered.
    """
    level = np.clip(np.round(np.log2(np.maximum(footprint, 1.0))), 0, len(levels) - 1).astype(np.int64)
    out = np.empty((len(x), 3), np.float32)
    tex = tex.astype(np.int32)
    for lv in np.flatnonzero(np.bincount(level, minlength=len(levels))):
        m = np.flatnonzero(level == lv)
        img = levels[lv]
        s = img.shape[1]  # a power of two: wrapping is a bit mask
        flat = img.reshape(-1, 3)
        xs = x[m].astype(np.float32) * np.float32(0.5 ** lv) - np.float32(0.5)
        ys = y[m].astype(np.float32) * np.float32(0.5 ** lv) - np.float32(0.5)
        x0, y0 = np.floor(xs), np.floor(ys)
        fx, fy = (xs - x0)[:, None], (ys - y0)[:, None]
        x0, y0 = x0.astype(np.int32) & (s - 1), y0.astype(np.int32) & (s - 1)
        x1, y1 = (x0 + 1) & (s - 1), (y0 + 1) & (s - 1)
        row0 = tex[m] * (s * s) + y0 * s
        row1 = row0 + (y1 - y0) * s
        top = flat.take(row0 + x0, 0).astype(np.float32)
        top += (flat.take(row0 + x1, 0) - top) * fx
        bottom = flat.take(row1 + x0, 0).astype(np.float32)
        bottom += (flat.take(row1 + x1, 0) - bottom) * fx
        top += (bottom - top) * fy
        top *= np.float32(1 / 255.0)
        out[m] = top
    return out
