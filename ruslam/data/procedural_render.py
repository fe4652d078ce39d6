"""Ray-caster of the procedural RGB-D scenes: plain-array `Scene`, camera helpers and vectorised `render`.

Conventions (used by `render`, `Scene` and `ruslam.data.procedural.ProceduralRGBD`):

- World frame: z up, the floor is z = 0.  Camera frame: OpenCV (x right, y down, z forward).
  ``T_world_cam`` (4x4) maps camera to world coordinates.
- Intrinsics ``K``: pinhole, square pixels, principal point at the image centre ((w-1)/2, (h-1)/2), i.e. pixel
  centres at integer coordinates; ``fx = (w/2) / tan(hfov/2)``.
- ``depth`` is the **z-depth** (distance along the optical axis, as Kinect/NYU/TUM store it), not the ray length.
  Rays are ``K^-1 [u, v, 1]``, whose camera z is 1, so the ray parameter of the hit is the z-depth exactly.
- Every surface is texture-mapped in its own coordinates, so texture stays fixed on it when the camera moves;
  textures are mip-mapped (`procedural_textures.sample_textures`) so they do not alias.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ruslam.data.height_field import first_crossing
from ruslam.data.procedural_textures import sample_textures, texture_bank

_EPS = 1e-4
# Texture axes (u, v) of a box face by its normal axis: x-faces use (y, -z), y-faces (x, -z), z-faces (x, y).
_U_AXIS = np.array([1, 0, 0])
_V_AXIS = np.array([2, 2, 1])
_V_SIGN = np.array([-1.0, -1.0, 1.0])


@dataclass
class Scene:
    """Plain arrays describing one scene; surface index k runs over boxes, then spheres, then height-fields.

    The room is box 0; a box that contains the camera is seen from inside (its inner faces are hit), which the
    renderer detects from the camera position.  Per surface: ``texel_density``
    (level-0 texels per metre), ``uv_angle`` (rad), ``uv_offset`` (texels) and ``tint`` (RGB gain).
    """

    box_center: np.ndarray  # [B, 3]
    box_half: np.ndarray  # [B, 3] half extents in the box frame
    box_yaw: np.ndarray  # [B] rotation about world z
    box_texture: np.ndarray  # [B, 6] texture index per face (axis * 2 + positive side)
    sphere_center: np.ndarray  # [S, 3]
    sphere_radius: np.ndarray  # [S]
    sphere_texture: np.ndarray  # [S]
    texel_density: np.ndarray  # [B + S + F]
    uv_angle: np.ndarray  # [B + S + F]
    uv_offset: np.ndarray  # [B + S + F, 2]
    tint: np.ndarray  # [B + S + F, 3]
    light_dir: np.ndarray  # [3] unit vector towards the light
    ambient: float
    T_world_cam: np.ndarray  # [4, 4] the scene's reference camera
    # Height-fields: floor patches centred at xy with half extents (hx, hy); heights (metres above z = 0) on a
    # regular G x G grid spanning the patch, interpolated bilinearly (edges 0, so patches meet the floor).
    field_center: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [F, 2]
    field_half: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [F, 2]
    field_heights: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))  # [F, G, G]
    field_texture: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [F]

    def render(self, T_world_cam: np.ndarray, K: np.ndarray, height: int, width: int,
               textures: tuple[np.ndarray, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
        return render(self, T_world_cam, K, height, width, textures)


def intrinsics(height: int, width: int, hfov_deg: float = 60.0) -> np.ndarray:
    f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def look_pose(position, yaw: float, pitch: float, roll: float = 0.0) -> np.ndarray:
    """T_world_cam of a camera at ``position`` heading ``yaw`` (rad, about z), ``pitch`` (rad, < 0 looks down)."""
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = position
    return T


def jitter_pose(T_world_cam: np.ndarray, rot_deg: float, trans_m: float, rng: np.random.Generator) -> np.ndarray:
    """Perturb a pose by a rotation of exactly ``rot_deg`` about a random axis and a translation of exactly
    ``trans_m`` in a random direction (both applied in the camera frame)."""
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    delta = np.eye(4)
    delta[:3, :3] = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(rot_deg))[0]
    delta[:3, 3] = direction / np.linalg.norm(direction) * trans_m
    return T_world_cam @ delta


def _yaw_matrices(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _screen_rect(c: np.ndarray, r: float, K: np.ndarray, height: int, width: int) -> tuple[slice, slice]:
    """Conservative pixel rectangle covering a sphere of radius r centred at c (camera frame) in front of it."""
    if c[2] - r <= 1e-3:
        return slice(0, height), slice(0, width)
    near, far = c[2] - r, c[2] + r
    span = []
    for axis, size in ((1, height), (0, width)):
        lo = (c[axis] - r) / (near if c[axis] - r < 0 else far)
        hi = (c[axis] + r) / (near if c[axis] + r > 0 else far)
        f, p = K[axis, axis], K[axis, 2]
        span.append(slice(int(np.clip(np.floor(f * lo + p), 0, size)), int(np.clip(np.ceil(f * hi + p) + 1, 0, size))))
    return span[0], span[1]



class _HeightField:
    """Bilinear height lookup of one height-field patch, prepared once per render (float32, flat grid)."""

    def __init__(self, scene: Scene, j: int):
        grid = np.asarray(scene.field_heights[j], np.float32)
        self.g, self.flat, self.top = grid.shape[0], grid.ravel(), float(grid.max())
        (cx, cy), (hx, hy) = scene.field_center[j], scene.field_half[j]
        self.x0, self.y0 = np.float32(cx - hx), np.float32(cy - hy)
        self.sx, self.sy = np.float32((self.g - 1) / (2 * hx)), np.float32((self.g - 1) / (2 * hy))
        self.lo = np.array([cx - hx, cy - hy, 0.0], np.float32)[:, None, None]
        self.hi = np.array([cx + hx, cy + hy, self.top + 1e-3], np.float32)[:, None, None]

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        limit = np.float32(self.g - 1 - 1e-3)
        gx = np.clip((x - self.x0) * self.sx, 0, limit)
        gy = np.clip((y - self.y0) * self.sy, 0, limit)
        ix, iy = gx.astype(np.int32), gy.astype(np.int32)
        fx, fy = gx - ix, gy - iy
        i00 = iy * self.g + ix
        h00, h01 = self.flat.take(i00), self.flat.take(i00 + 1)
        h10, h11 = self.flat.take(i00 + self.g), self.flat.take(i00 + self.g + 1)
        top = h00 + (h01 - h00) * fx
        return top + (h10 + (h11 - h10) * fx - top) * fy


def _field_hits(hf: _HeightField, o: np.ndarray, dk: np.ndarray, steps: int = 12, bisections: int = 6) -> np.ndarray:
    """Ray parameter of the first crossing of a height-field (inf if none): ``steps`` uniform samples between
    entering and leaving the patch's bounding box find the first sample below the surface, bisection narrows
    the bracket 64-fold, and a final secant step on the (locally planar) surface makes the error sub-millimetre
    (tested).  Bumps thinner than a sample step can be missed; the generated bumps are far wider."""
    d_safe = np.where(np.abs(dk) < 1e-12, np.float32(1e-12), dk)
    o32 = o.astype(np.float32)
    t1, t2 = (hf.lo - o32[:, None, None]) / d_safe, (hf.hi - o32[:, None, None]) / d_safe
    t_in = np.maximum(np.minimum(t1, t2).max(0), _EPS)
    t_out = np.maximum(t1, t2).min(0)
    tk = np.full(t_in.shape, np.inf, np.float32)
    sel = np.flatnonzero(t_in < t_out)
    if sel.size == 0:
        return tk
    dd = dk.reshape(3, -1)[:, sel]

    def above(t):  # ray height minus terrain height at ray parameter t
        return o32[2] + t * dd[2] - hf(o32[0] + t * dd[0], o32[1] + t * dd[1])

    t, found = first_crossing(above, t_in.ravel()[sel], (t_out - t_in).ravel()[sel], samples=steps,
                              splits=bisections, method="bisection", min_drop=1e-12)
    tk.reshape(-1)[sel[found]] = t[found]
    return tk


def render(scene: Scene, T_world_cam: np.ndarray, K: np.ndarray, height: int, width: int,
           textures: tuple[np.ndarray, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast ``scene`` -> (image float32 HxWx3 in [0, 1], z-depth float32 HxW metres; NaN where no surface).

    ``textures`` are the mip levels of a texture bank (`procedural_textures.texture_bank`), default seed 0.
    """
    K = np.asarray(K, np.float64)
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    x_cam = ((np.arange(width) - K[0, 2]) / K[0, 0]).astype(np.float32)[None, None, :]
    y_cam = ((np.arange(height) - K[1, 2]) / K[1, 1]).astype(np.float32)[None, :, None]
    R32 = R.astype(np.float32)[:, :, None, None]
    d = R32[:, 0] * x_cam + R32[:, 1] * y_cam + R32[:, 2]  # [3, H, W] world ray directions whose camera-z is 1

    n_box, n_sph, n_fld = len(scene.box_center), len(scene.sphere_center), len(scene.field_center)
    Rb = _yaw_matrices(scene.box_yaw)
    fields = [_HeightField(scene, j) for j in range(n_fld)]
    field_top = np.array([hf.top for hf in fields])
    radius = np.concatenate([np.linalg.norm(scene.box_half, axis=1), scene.sphere_radius,
                             np.linalg.norm(np.column_stack([scene.field_half, field_top / 2]), axis=1)])
    centre = np.concatenate([scene.box_center, scene.sphere_center,
                             np.column_stack([scene.field_center, field_top / 2]).reshape(n_fld, 3)])
    t = np.full((height, width), np.inf, np.float32)  # nearest hit so far and its surface index
    surface = np.zeros((height, width), np.int64)
    for k in range(n_box + n_sph + n_fld):
        rows, cols = _screen_rect(R.T @ (centre[k] - o), radius[k], K, height, width)
        if rows.start >= rows.stop or cols.start >= cols.stop:
            continue
        dk = d[:, rows, cols]
        if k < n_box:  # slab test in the box's own frame
            d_loc = dk.copy() if scene.box_yaw[k] == 0 else np.einsum("ji,jhw->ihw", Rb[k].astype(np.float32), dk)
            o_loc = (Rb[k].T @ (o - centre[k])).astype(np.float32)[:, None, None]
            half = scene.box_half[k].astype(np.float32)[:, None, None]
            d_loc[np.abs(d_loc) < 1e-12] = 1e-12  # axis-parallel rays: no division by zero, slab at infinity
            inv = 1.0 / d_loc
            if (np.abs(o_loc) < half).all():  # camera inside (the room): every ray exits through one face
                tk = ((np.where(d_loc > 0, half, -half) - o_loc) * inv).min(0)
            else:
                t1, t2 = (-half - o_loc) * inv, (half - o_loc) * inv
                t_near, t_far = np.minimum(t1, t2).max(0), np.maximum(t1, t2).min(0)
                tk = np.where((t_near > _EPS) & (t_near <= t_far), t_near, np.inf)
        elif k >= n_box + n_sph:
            tk = _field_hits(fields[k - n_box - n_sph], o, dk)
        else:  # nearest root of |o + t d - c|^2 = r^2
            oc = (o - centre[k]).astype(np.float32)
            a = (dk * dk).sum(0)
            b = np.einsum("i,ihw->hw", oc, dk)
            disc = b * b - a * np.float32(oc @ oc - radius[k] ** 2)
            tk = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            tk[(disc < 0) | (tk <= _EPS)] = np.inf
        closer = tk < t[rows, cols]
        t[rows, cols] = np.where(closer, tk, t[rows, cols])
        surface[rows, cols][closer] = k
    t, surface, d = t.ravel(), surface.ravel(), d.reshape(3, -1)
    hit = np.isfinite(t)
    idx = slice(None) if hit.all() else np.flatnonzero(hit)
    k, t_hit, d_hit = surface[idx], t[idx], d[:, idx]
    n_hit = k.size

    # Per-surface tables in float32, gathered per pixel by surface index k.
    f32 = np.float32
    cos_yaw, sin_yaw = np.cos(scene.box_yaw).astype(f32), np.sin(scene.box_yaw).astype(f32)
    uv_cos = np.cos(scene.uv_angle).astype(f32)
    uv_sin = np.sin(scene.uv_angle).astype(f32)
    rho_k = scene.texel_density.astype(f32)
    offset_k = scene.uv_offset.astype(f32)

    # Surface frame of every hit pixel, boxes and spheres each in one vectorised pass.
    rel = o.astype(f32)[:, None] + t_hit * d_hit - centre.astype(f32)[k].T
    normal, tex = np.empty((3, n_hit), f32), np.empty(n_hit, np.int64)
    su, sv = np.empty(n_hit, f32), np.empty(n_hit, f32)  # surface coordinates, metres
    b = np.flatnonzero(k < n_box)
    kb = k[b]
    c, s = cos_yaw[kb], sin_yaw[kb]
    p = np.stack([c * rel[0, b] + s * rel[1, b], -s * rel[0, b] + c * rel[1, b], rel[2, b]])  # box frame
    axis = np.argmax(np.abs(p) * (1.0 / scene.box_half.astype(f32))[kb].T, axis=0)
    ar = np.arange(b.size)
    positive = p[axis, ar] > 0
    sign = np.where(positive, f32(1), f32(-1))
    zero = f32(0)
    normal[0, b] = np.where(axis == 0, c, np.where(axis == 1, -s, zero)) * sign  # yaw applied to the face axis
    normal[1, b] = np.where(axis == 0, s, np.where(axis == 1, c, zero)) * sign
    normal[2, b] = (axis == 2) * sign
    tex[b] = scene.box_texture[kb, axis * 2 + positive]
    su[b] = p[_U_AXIS[axis], ar]
    sv[b] = p[_V_AXIS[axis], ar] * _V_SIGN.astype(f32)[axis]
    q = np.flatnonzero((k >= n_box) & (k < n_box + n_sph))
    if q.size:
        r = radius.astype(f32)[k[q]]
        p = rel[:, q] / r
        normal[:, q] = p
        tex[q] = scene.sphere_texture[k[q] - n_box]
        su[q] = r * np.arctan2(p[1], p[0])
        sv[q] = -r * np.arcsin(np.clip(p[2], -1.0, 1.0))
    for j in range(n_fld):  # height-fields: texture in floor coordinates, normal from central differences
        g = np.flatnonzero(k == n_box + n_sph + j)
        px, py = rel[0, g] + centre[n_box + n_sph + j, 0], rel[1, g] + centre[n_box + n_sph + j, 1]
        e = f32(0.01)
        gx = (fields[j](px + e, py) - fields[j](px - e, py)) / (2 * e)
        gy = (fields[j](px, py + e) - fields[j](px, py - e)) / (2 * e)
        nz = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
        normal[:, g] = np.stack([-gx * nz, -gy * nz, nz])
        tex[g] = scene.field_texture[j]
        su[g], sv[g] = rel[0, g], rel[1, g]

    # Texture coordinates in level-0 texels; footprint = texels covered by one pixel (picks the mip level).
    ca, sa, rho = uv_cos[k], uv_sin[k], rho_k[k]
    x = rho * (ca * su - sa * sv) + offset_k[k, 0]
    y = rho * (sa * su + ca * sv) + offset_k[k, 1]
    cos_view = (normal * d_hit).sum(0) / np.sqrt((d_hit * d_hit).sum(0))
    footprint = rho * t_hit / f32(K[0, 0]) / np.maximum(np.abs(cos_view), f32(0.25))
    albedo = sample_textures(textures or texture_bank(0), tex, x, y, footprint)
    # Two-sided Lambertian: the normal is flipped to face the camera before lighting.
    lit = np.maximum((scene.light_dir.astype(f32) @ normal) * -np.sign(cos_view + f32(1e-12)), zero)
    shade = f32(scene.ambient) + f32(1.0 - scene.ambient) * lit
    albedo *= scene.tint.astype(f32)[k]
    albedo *= shade[:, None]
    image = np.zeros((t.size, 3), f32)
    image[idx] = np.clip(albedo, 0.0, 1.0, out=albedo)
    depth = np.where(hit, t, np.nan).astype(f32)
    return image.reshape(height, width, 3), depth.reshape(height, width)
