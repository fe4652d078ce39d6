"""A tiled pool: a flat floor and four walls covered with square tiles and light grout, as in the real pool
footage (repetitive texture, a forward-looking camera that sees the walls when it turns towards them).

The pool is a box ray-cast analytically: each pixel's ray meets the floor plane or one of the wall planes; a ray that
leaves the box above the walls (the water surface) sees open water (infinite range). Albedo comes from two
mip-mapped textures, one for the floor and one for the walls, so grazing views of far tiles are filtered instead
of aliasing. Besides each tile's shade and speckle, low-frequency stains and a few pale patches are all that tells
one stretch of tiles from another.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ruslam.data.synthetic_sequence import _fractal, _sample_mipmapped, texture_pyramid

DEPTH_M = 1.6  # wall height: the real pool is 1.6 m deep
MARGIN_M = 1.2  # floor between the path's extent and the walls
TEXEL_M = 0.002  # texture resolution: below a pixel's footprint on the nearest floor the camera sees
GROUT = 0.12  # grout line width as a fraction of the tile
MOTTLE = 0.15  # the tiles' speckle: in-tile contrast as in the real pool footage (std / mean ~0.07)


@dataclass
class TiledPool:
    """The box [-half_x, half_x] x [-half_y, half_y] x [0, DEPTH_M] and its textures' mip-map levels."""

    half_x: float
    half_y: float
    floor_levels: list[np.ndarray]  # over the floor: texel (i, j) at (x, y) = (j + 0.5, i + 0.5) * TEXEL_M - half
    wall_levels: list[np.ndarray]  # over the four walls unrolled: columns along them, rows from the top edge down


def _tiles(rng: np.random.Generator, width_m: float, height_m: float, tile_m: float) -> np.ndarray:
    """uint8 RGB texture of ``width_m`` x ``height_m`` metres: dark mottled tiles of ``tile_m`` in light grout, with
    stains and a few pale patches."""
    w, h = int(np.ceil(width_m / TEXEL_M)), int(np.ceil(height_m / TEXEL_M))
    period = tile_m / TEXEL_M
    u, v = np.arange(w, dtype=np.float32) / period, np.arange(h, dtype=np.float32) / period
    grout = (np.minimum(u % 1, 1 - u % 1) < GROUT / 2)[None, :] | (np.minimum(v % 1, 1 - v % 1) < GROUT / 2)[:, None]
    tone = rng.normal(0.0, 0.04, (int(v[-1]) + 1, int(u[-1]) + 1)).astype(np.float32)  # each tile its own shade
    albedo = 0.28 + tone[v.astype(int)[:, None], u.astype(int)[None, :]]
    speck = rng.normal(0.0, 1.0, (int(h / period * 6) + 1, int(w / period * 6) + 1)).astype(np.float32)
    albedo *= 1.0 + MOTTLE * cv2.resize(speck, (w, h), interpolation=cv2.INTER_CUBIC)  # blobs a sixth of a tile
    albedo = np.where(grout, 0.78, albedo)
    side = max(width_m, height_m)  # isotropic stains: one square of noise over the longer side, cropped
    stains = _fractal(rng, 256, octaves=4, base=4)[:max(2, int(256 * height_m / side)),
                                                   :max(2, int(256 * width_m / side))]
    albedo *= 1.0 + 0.25 * cv2.resize(stains, (w, h), interpolation=cv2.INTER_CUBIC)
    patches = np.zeros((h, w), np.float32)  # pale patches (silt, repairs): about one per 2 m²
    for _ in range(max(1, int(round(width_m * height_m / 2.0)))):
        centre = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        axes = (int(rng.uniform(0.08, 0.25) / TEXEL_M), int(rng.uniform(0.05, 0.15) / TEXEL_M))
        cv2.ellipse(patches, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1.0, -1)
    albedo += 0.25 * cv2.GaussianBlur(patches, (0, 0), 4)
    tint = np.array([0.85, 0.95, 1.0], np.float32)  # slightly blue tiles
    return (np.clip(albedo[..., None] * tint, 0, 1) * 255).astype(np.uint8)


def make_pool(path_xy: np.ndarray, tile_m: float, seed: int) -> TiledPool:
    """The pool around a path (its [N, 2] positions): the path's extent plus ``MARGIN_M`` on every side."""
    rng = np.random.default_rng(seed)
    half_x = float(np.abs(path_xy[:, 0]).max() + MARGIN_M)
    half_y = float(np.abs(path_xy[:, 1]).max() + MARGIN_M)
    floor = _tiles(rng, 2 * half_x, 2 * half_y, tile_m)
    walls = _tiles(rng, 4 * (half_x + half_y), DEPTH_M, tile_m)  # the four walls unrolled side by side
    return TiledPool(half_x, half_y, texture_pyramid(floor), texture_pyramid(walls))


def render_pool(pool: TiledPool, rays: np.ndarray, T_world_cam: np.ndarray):
    """Ray-cast one view from inside the pool -> (RGB float32 [H, W, 3] in [0, 1], range [H, W] metres; open water:
    black, infinite range)."""
    d = (rays @ T_world_cam[:3, :3].T).astype(np.float64)
    o = T_world_cam[:3, 3].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(d[..., 2] < 0, -o[2] / d[..., 2], np.inf)
        # the walls x = +-half_x, y = +-half_y: the one each ray heads towards
        t_x = np.where(d[..., 0] != 0, (np.sign(d[..., 0]) * pool.half_x - o[0]) / d[..., 0], np.inf)
        t_y = np.where(d[..., 1] != 0, (np.sign(d[..., 1]) * pool.half_y - o[1]) / d[..., 1], np.inf)
    t_wall = np.minimum(t_x, t_y)
    on_floor = t_floor <= t_wall
    t = np.where(on_floor, t_floor, t_wall)
    z = o[2] + t * d[..., 2]
    open_water = ~on_floor & (z > DEPTH_M)

    # floor texture coordinates of every ray (the plane beyond the walls too, so the mip level is smooth)
    t_plane = np.where(np.isfinite(t_floor), t_floor, 1e3)
    fx = ((o[0] + t_plane * d[..., 0] + pool.half_x) / TEXEL_M - 0.5).astype(np.float32)
    fy = ((o[1] + t_plane * d[..., 1] + pool.half_y) / TEXEL_M - 0.5).astype(np.float32)
    rgb = _sample_mipmapped(pool.floor_levels, fx, fy)

    # wall texture: the coordinate along the unrolled walls (x+, y+, x-, y-) and the depth below the top edge
    x, y = o[0] + t_wall * d[..., 0], o[1] + t_wall * d[..., 1]
    hx, hy = pool.half_x, pool.half_y
    along = np.where(t_x <= t_y,
                     np.where(d[..., 0] > 0, y + hy, 2 * hy + 2 * hx + (hy - y)),
                     np.where(d[..., 1] > 0, 2 * hy + (hx - x), 4 * hy + 2 * hx + (x + hx)))
    wx = (np.nan_to_num(along, posinf=0, neginf=0) / TEXEL_M - 0.5).astype(np.float32)
    wy = (np.clip(np.nan_to_num(DEPTH_M - (o[2] + t_wall * d[..., 2])), -1, 2 * DEPTH_M) / TEXEL_M - 0.5)
    wall_rgb = _sample_mipmapped(pool.wall_levels, wx, wy.astype(np.float32))
    rgb = np.where(on_floor[..., None], rgb, wall_rgb)
    rgb[open_water] = 0.0
    t = np.where(open_water, np.inf, t).astype(np.float32)
    return rgb, t
