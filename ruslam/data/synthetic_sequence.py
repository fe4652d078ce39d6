"""The embedded SLAM default: a camera flying a closed circuit over a textured seafloor with rocks.

The seafloor is a metric height field (undulating sand + rock domes) with a baked-shading albedo texture; frames are
ray-cast against it (coarse march + regula falsi, vectorised with `cv2.remap` lookups), so poses and ranges are
exact. The clean ("clear") render is written first in the EuRoC layout with per-pixel range; every turbid level is
derived from it by the pseudo-underwater model (`ruslam.data.synthesis.degrade`, eq. 4) on first use, so each
level is a plain EuRoC folder that `read_euroc` loads. The circuit ends past its start, so a loop closure exists.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ruslam.data.camera import Camera
from ruslam.data.height_field import first_crossing
from ruslam.data.readers import Sequence, read_euroc
from ruslam.errors import InputError, MissingInput

VERSION = 1  # bump when rendering changes, so stale caches are regenerated
DEPTH_SCALE = 10000.0  # uint16 range PNG units per metre (0.1 mm; up to 6.5 m)


@dataclass(frozen=True)
class SeafloorConfig:
    """Everything that determines the clean render; its hash names the cache folder."""

    num_frames: int = 300
    stereo: bool = False
    baseline: float = 0.12  # metres, right camera along +x of the left one
    width: int = 640
    height: int = 480
    focal: float = 450.0
    fps: float = 10.0
    altitude: float = 2.0  # metres above the mean seafloor
    radii: tuple[float, float] = (3.0, 2.0)  # ellipse of the circuit (metres)
    laps: float = 1.12  # > 1: the end revisits the start (loop closure)
    pitch_deg: float = 10.0  # forward tilt of the downward-looking camera
    num_rocks: int = 70
    half_extent: float = 6.5  # the seafloor covers [-half, half]^2 metres
    height_res: int = 1300  # height-field samples per side (1 cm)
    texture_res: int = 4096  # albedo texels per side (3.2 mm, about one pixel at 2 m)
    seed: int = 0

    def key(self) -> str:
        text = json.dumps({**asdict(self), "version": VERSION}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:10]

    def camera(self) -> Camera:
        return Camera(self.width, self.height, self.focal, self.focal, (self.width - 1) / 2, (self.height - 1) / 2)


# ------------------------------------------------------------------------------------------------- the seafloor


@dataclass
class Seafloor:
    """Height field [G, G] (metres) and albedo texture [T, T, 3] (uint8 RGB) over the square [-half, half]^2."""

    height: np.ndarray
    texture: np.ndarray
    half: float

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        g = self.height.shape[0] / (2 * self.half)
        return cv2.remap(self.height, ((x + self.half) * g - 0.5).astype(np.float32),
                         ((y + self.half) * g - 0.5).astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)


def _fractal(rng: np.random.Generator, size: int, octaves: int, base: int = 8) -> np.ndarray:
    """Smooth value noise in [-1, 1] at ``size``^2: sum of upsampled random grids, halving amplitude per octave."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for k in range(octaves):
        cells = base * 2**k
        grid = rng.standard_normal((cells, cells)).astype(np.float32)
        out += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.55
    return np.clip(out / (total * 1.5), -1, 1)


def make_seafloor(cfg: SeafloorConfig, num_pebbles: int = 12000) -> Seafloor:
    """The seafloor of ``cfg`` (seeded); ``num_pebbles`` sets how densely small pebbles/shells cover the sand."""
    rng = np.random.default_rng(cfg.seed)
    half, height_res, tex_res = cfg.half_extent, cfg.height_res, cfg.texture_res
    res = 2 * half / height_res
    sand_height = 0.12 * _fractal(rng, height_res, 3, base=4)  # gentle sand undulation
    rock_relief = 0.05 * _fractal(rng, height_res, 4, base=40)  # knobbly rock surfaces
    height = sand_height.copy()
    rock_tint = np.zeros((height_res, height_res, 4), np.float32)  # rgb tint + coverage
    for _ in range(cfg.num_rocks):
        cx, cy = rng.uniform(-half + 0.6, half - 0.6, 2)
        rx, ry = rng.uniform(0.12, 0.55, 2)
        h = rng.uniform(0.08, 0.4) * min(1.0, (rx + ry) / 0.6)
        angle = rng.uniform(0, np.pi)
        tint = rng.uniform(0.4, 0.7) * np.array([1.0, 1.0, 0.88]) * rng.uniform(0.93, 1.05, 3)
        i0, i1 = (np.clip([(cy - 0.6 + half) / res, (cy + 0.6 + half) / res], 0, height_res)).astype(int)
        j0, j1 = (np.clip([(cx - 0.6 + half) / res, (cx + 0.6 + half) / res], 0, height_res)).astype(int)
        Y, X = np.mgrid[i0:i1, j0:j1].astype(np.float32)
        X, Y = (X + 0.5) * res - half - cx, (Y + 0.5) * res - half - cy
        u = (X * np.cos(angle) + Y * np.sin(angle)) / rx
        v = (-X * np.sin(angle) + Y * np.cos(angle)) / ry
        inside = u * u + v * v < 1.0
        dome = h * np.clip(1.0 - (u * u + v * v), 0, 1) ** 0.5 * (1 + 5 * rock_relief[i0:i1, j0:j1])
        dome += sand_height[i0:i1, j0:j1]
        height[i0:i1, j0:j1] = np.where(inside, np.maximum(height[i0:i1, j0:j1], dome), height[i0:i1, j0:j1])
        rock_tint[i0:i1, j0:j1] = np.where(inside[..., None], [*tint, 1.0], rock_tint[i0:i1, j0:j1])
    height = cv2.GaussianBlur(height, (0, 0), 1.0)  # round the rock rims a little (1 cm)

    # Albedo at texture resolution: sand colour field, pebbles/shells, speckled rocks, baked Lambert shading.
    grain = cv2.GaussianBlur(rng.standard_normal((tex_res, tex_res)).astype(np.float32), (0, 0), 1.2)
    detail = 0.18 * _fractal(rng, tex_res, 6, base=6) + 0.25 * _fractal(rng, tex_res, 3, base=96) + 0.35 * grain
    sand = np.array([0.55, 0.5, 0.4], np.float32) * (1 + detail)[..., None]
    sand *= (1 + 0.3 * _fractal(rng, tex_res // 4, 2, base=3))[..., None].repeat(4, 0).repeat(4, 1)  # patches
    tex = np.clip(sand, 0, 1)
    n_pebbles = int(num_pebbles)
    centres = rng.integers(0, tex_res, (n_pebbles, 2))
    axes = rng.integers(2, 10, (n_pebbles, 2))
    shades = rng.uniform(0.25, 0.9, (n_pebbles, 1)) * [0.95, 0.9, 0.8] * rng.uniform(0.93, 1.07, (n_pebbles, 3))
    for (x, y), ax, ang, col in zip(centres, axes, rng.uniform(0, 180, n_pebbles), shades, strict=True):
        cv2.ellipse(tex, (int(x), int(y)), (int(ax[0]), int(ax[1])), float(ang), 0, 360,
                    tuple(float(c) for c in col), -1, lineType=cv2.LINE_AA)
    tint = cv2.resize(rock_tint, (tex_res, tex_res), interpolation=cv2.INTER_LINEAR)
    speckle = 1 + (0.4 * _fractal(rng, tex_res, 7, base=24) + 0.3 * grain)[..., None]
    tex = tex * (1 - tint[..., 3:]) + np.clip(tint[..., :3] * speckle, 0, 1)
    h_hi = cv2.resize(height, (tex_res, tex_res), interpolation=cv2.INTER_CUBIC)
    step = 2 * half / tex_res
    gx = cv2.Sobel(h_hi, cv2.CV_32F, 1, 0, ksize=3) / (8 * step)
    gy = cv2.Sobel(h_hi, cv2.CV_32F, 0, 1, ksize=3) / (8 * step)
    light = np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0])
    lambert = (-gx * light[0] - gy * light[1] + light[2]) / np.sqrt(gx * gx + gy * gy + 1)
    tex *= (0.3 + 0.8 * np.clip(lambert, 0, 1))[..., None]
    texture = np.clip(tex * 255 + 0.5, 0, 255).astype(np.uint8)
    return Seafloor(height=height.astype(np.float32), texture=texture, half=half)


# ---------------------------------------------------------------------------------------------------- the path


def circuit_poses(cfg: SeafloorConfig) -> np.ndarray:
    """T_world_cam0 [N, 4, 4] along an ellipse flown ``laps`` times, heading along the tangent, looking down."""
    s = np.linspace(0, 2 * np.pi * cfg.laps, cfg.num_frames)
    a, b = cfg.radii
    pos = np.stack([a * np.cos(s), b * np.sin(s), cfg.altitude + 0.15 * np.sin(3 * s)], axis=1)
    fwd = np.stack([-a * np.sin(s), b * np.cos(s), np.zeros_like(s)], axis=1)
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    return downward_poses(pos, fwd, cfg.pitch_deg, np.deg2rad(2.0) * np.sin(5 * s))


def downward_poses(positions: np.ndarray, forward: np.ndarray, pitch_deg: float, roll: np.ndarray) -> np.ndarray:
    """T_world_cam [N, 4, 4] of a camera at ``positions`` [N, 3] looking down, its optical axis tilted
    ``pitch_deg`` from straight down towards the horizontal unit ``forward`` [N, 3] (image down = backwards), then
    rolled by ``roll`` [N] radians about the optical axis."""
    up = np.array([0.0, 0.0, 1.0])
    p = np.deg2rad(pitch_deg)
    z_c = -np.cos(p) * up + np.sin(p) * forward  # optical axis: down, tilted forward
    y_c = -np.cos(p) * forward - np.sin(p) * up  # image down = backwards
    R = np.stack([np.cross(y_c, z_c), y_c, z_c], axis=2)
    poses = np.tile(np.eye(4), (len(positions), 1, 1))
    poses[:, :3, :3] = R @ Rotation.from_rotvec(roll[:, None] * up).as_matrix()
    poses[:, :3, 3] = positions
    return poses


# -------------------------------------------------------------------------------------------------- rendering


def pixel_rays(camera: Camera) -> np.ndarray:
    """Unit viewing rays [H, W, 3] of every pixel in the camera frame (a distorted camera's pixels through its
    undistortion, so the rendered image carries the lens distortion exactly)."""
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float32), np.arange(camera.height, dtype=np.float32))
    if camera.distorted:
        ideal = camera.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(*u.shape, 2)
        u, v = ideal[..., 0].astype(np.float32), ideal[..., 1].astype(np.float32)
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def render(floor: Seafloor, rays: np.ndarray, T_world_cam: np.ndarray, steps: int = 12, refine: int = 3,
           texture_levels: list[np.ndarray] | None = None, max_incidence_deg: float | None = None):
    """Ray-cast one view -> (RGB float32 [H, W, 3] in [0, 1], range [H, W] metres along each pixel's ray).

    ``texture_levels`` (`texture_pyramid`) filters the texture by each pixel's footprint (mip-mapping), so grazing
    views of a far floor do not alias into flickering noise. ``max_incidence_deg``: rays closer to the horizon
    than this (angle from straight down) see nothing (black, infinite range), instead of raising.
    """
    d = rays @ T_world_cam[:3, :3].T.astype(np.float32)
    o = T_world_cam[:3, 3].astype(np.float32)
    void = None
    if max_incidence_deg is not None:
        z_max = -np.cos(np.deg2rad(max_incidence_deg))
        void = d[..., 2] > z_max
        d[..., 2] = np.minimum(d[..., 2], z_max)
    if np.any(d[..., 2] >= -1e-3):
        raise ValueError("render() needs a downward-looking camera: some pixel rays do not point down.")
    g = floor.height.shape[0] / (2 * floor.half)
    x0, y0 = (o[0] + floor.half) * g - 0.5, (o[1] + floor.half) * g - 0.5
    dx, dy, dz = d[..., 0] * g, d[..., 1] * g, d[..., 2]

    def gap(t):  # ray height above the floor at parameter t (metres along the ray)
        h = cv2.remap(floor.height, x0 + t * dx, y0 + t * dy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return o[2] + t * dz - h

    t_top = (o[2] - float(floor.height.max())) / -dz  # the march spans the floor's height range
    span = (o[2] - float(floor.height.min())) / -dz - t_top
    t, _ = first_crossing(gap, t_top, span, samples=steps + 1, splits=refine, method="false_position", min_drop=1e-9)
    tg = floor.texture.shape[0] / (2 * floor.half)
    tx = (o[0] + t * d[..., 0] + floor.half) * tg - 0.5
    ty = (o[1] + t * d[..., 1] + floor.half) * tg - 0.5
    if texture_levels is None:
        rgb = cv2.remap(floor.texture, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        rgb = rgb.astype(np.float32) / 255.0
    else:
        rgb = _sample_mipmapped(texture_levels, tx, ty)
    if void is not None:
        rgb[void], t[void] = 0.0, np.inf
    return rgb, t


def texture_pyramid(texture: np.ndarray, levels: int = 6) -> list[np.ndarray]:
    """The texture and its successive 2x reductions (level k: one texel = 2^k texels of level 0)."""
    out = [texture]
    for _ in range(levels - 1):
        out.append(cv2.pyrDown(out[-1]))
    return out


def _sample_mipmapped(levels: list[np.ndarray], tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Trilinear texture lookup: the level is log2 of the pixel footprint in texels (from neighbouring pixels)."""
    du = np.hypot(np.gradient(tx, axis=1), np.gradient(ty, axis=1))
    dv = np.hypot(np.gradient(tx, axis=0), np.gradient(ty, axis=0))
    level = np.clip(np.log2(np.maximum(np.maximum(du, dv), 1e-6)), 0, len(levels) - 1)
    lo = np.floor(level).astype(int)
    hi = np.minimum(lo + 1, len(levels) - 1)
    frac = (level - lo)[..., None]
    rgb = np.zeros((*tx.shape, 3), np.float32)
    for k in np.unique(np.concatenate([lo.ravel(), hi.ravel()])):
        s = 2.0**-k
        sample = cv2.remap(levels[k], ((tx + 0.5) * s - 0.5).astype(np.float32),
                           ((ty + 0.5) * s - 0.5).astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        weight = np.where(lo[..., None] == k, 1 - frac, 0) + np.where(hi[..., None] == k, frac, 0)
        rgb += weight.astype(np.float32) * (sample.astype(np.float32) / 255.0)
    return rgb


# ------------------------------------------------------------------------------------------ writing / turbidity


@dataclass(frozen=True)
class WaterLevel:
    """One turbidity level of eq. 4: a Jerlov water type (None = the clean in-air render) and its other terms."""

    water: str | None = None
    light: float = 1.0  # L: extra illumination factor, < 1 for low light
    background: tuple[float, float, float] | None = None  # A (RGB); None: ambient daylight colour at ambient_depth_m
    ambient_depth_m: float = 5.0
    noise_std: float = 0.01
    blur_angle_deg: float = 20.0
    blur_length: float = 4.0

    def key(self) -> str:
        return hashlib.sha1(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:8]

    def background_light(self) -> np.ndarray:
        """A = 0.7 eta, eta the colour daylight keeps after ``ambient_depth_m`` of this water (synthesis defaults)."""
        if self.background is not None:
            return np.asarray(self.background, np.float32)
        from ruslam.data.background_light import DEFAULT_L, ambient_rgb  # noqa: PLC0415

        rgb = ambient_rgb(self.water, self.ambient_depth_m)
        return (DEFAULT_L * rgb / rgb.max()).astype(np.float32)


#: The default sweep: clear water, Jerlov open-ocean I and III, coastal 5C and 9C, and a dim coastal scene.
LEVELS = {
    "clear": WaterLevel(),
    "jerlov_I": WaterLevel("I"),
    "jerlov_III": WaterLevel("III"),
    "jerlov_5C": WaterLevel("5C"),
    "jerlov_9C": WaterLevel("9C"),
    "low_light": WaterLevel("5C", light=0.3),
}


def _sensor_yaml(camera: Camera, T_BS: np.ndarray, fps: float, comment: str) -> str:
    data = ", ".join(f"{x:.9g}" for x in T_BS.ravel())
    return (f"sensor_type: camera\ncomment: {comment}\nT_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"
            f"rate_hz: {fps:g}\nresolution: [{camera.width}, {camera.height}]\ncamera_model: pinhole\n"
            f"intrinsics: [{camera.fx:.9g}, {camera.fy:.9g}, {camera.cx:.9g}, {camera.cy:.9g}]\n"
            "distortion_model: radial-tangential\n"
            f"distortion_coefficients: [{', '.join(f'{d:.9g}' for d in camera.dist[:4])}]\n")


def _stamps_ns(cfg: SeafloorConfig) -> np.ndarray:
    return 1_000_000_000 + np.round(np.arange(cfg.num_frames) * 1e9 / cfg.fps).astype(np.int64)


def _write_layout(root: Path, cfg: SeafloorConfig, poses: np.ndarray, level: str) -> list[Path]:
    """EuRoC skeleton: sensor.yaml + data.csv per camera and the ground truth csv; returns the camera folders."""
    camera, stamps = cfg.camera(), _stamps_ns(cfg)
    T_BS = [np.eye(4)]
    if cfg.stereo:
        T_BS.append(np.eye(4))
        T_BS[1][0, 3] = cfg.baseline
    cam_dirs = []
    for c, T in enumerate(T_BS):
        cam_dir = root / "mav0" / f"cam{c}"
        (cam_dir / "data").mkdir(parents=True)
        side = ("left", "right")[c]
        (cam_dir / "sensor.yaml").write_text(_sensor_yaml(camera, T, cfg.fps, f"ruslam seafloor {level} {side}"))
        (cam_dir / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in stamps))
        cam_dirs.append(cam_dir)
    gt_dir = root / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir(parents=True)
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
    rows = [f"{t},{p[0]:.9f},{p[1]:.9f},{p[2]:.9f},{w:.12f},{x:.12f},{y:.12f},{z:.12f}" + ",0" * 9
            for t, p, (w, x, y, z) in zip(stamps, poses[:, :3, 3], q, strict=True)]
    header = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
    (gt_dir / "data.csv").write_text(header + ", v_RS_R_x, v_RS_R_y, v_RS_R_z, b_w_x, b_w_y, b_w_z, b_a_x, b_a_y, "
                                     "b_a_z\n" + "\n".join(rows) + "\n")
    return cam_dirs


def _publish(tmp: Path, final: Path) -> None:
    """Atomic hand-over: a half-written folder never carries the final name."""
    try:
        tmp.rename(final)
    except OSError:  # another process finished first
        shutil.rmtree(tmp, ignore_errors=True)
        if not final.is_dir():
            raise


def render_clean(cfg: SeafloorConfig, out: Path, progress: bool = False) -> Path:
    """Render the clean sequence (images + uint16 range maps in ``depth<c>/``) into ``out`` in the EuRoC layout."""
    if out.is_dir():
        return out
    tmp = out.with_name(out.name + f".tmp{np.random.default_rng().integers(1 << 30)}")
    floor = make_seafloor(cfg)
    poses = circuit_poses(cfg)
    cam_dirs = _write_layout(tmp, cfg, poses, "clear")
    rays = pixel_rays(cfg.camera())
    offsets = [np.eye(4)] + ([_right_offset(cfg)] if cfg.stereo else [])
    stamps = _stamps_ns(cfg)
    frames = range(cfg.num_frames)
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        frames = tqdm(frames, desc="rendering seafloor", unit="frame")
    for i in frames:
        for cam_dir, offset in zip(cam_dirs, offsets, strict=True):
            rgb, rng = render(floor, rays, poses[i] @ offset)
            depth_dir = cam_dir.parent / cam_dir.name.replace("cam", "depth") / "data"
            depth_dir.mkdir(parents=True, exist_ok=True)
            _imwrite(cam_dir / "data" / f"{stamps[i]}.png", rgb)
            depth = np.clip(rng * DEPTH_SCALE + 0.5, 0, 65535).astype(np.uint16)
            cv2.imwrite(str(depth_dir / f"{stamps[i]}.png"), depth)
    _publish(tmp, out)
    return out


def _right_offset(cfg: SeafloorConfig) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = cfg.baseline
    return T


def _imwrite(path: Path, rgb: np.ndarray) -> None:
    image = np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8)[..., ::-1]
    cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 1])


def degrade_level(cfg: SeafloorConfig, clean: Path, level: WaterLevel, out: Path, progress: bool = False) -> Path:
    """Apply eq. 4 (``ruslam.data.synthesis.degrade``) to every clean frame; noise seeded by (seed, frame)."""
    if out.is_dir():
        return out
    try:
        import torch  # noqa: PLC0415

        from ruslam.data.synthesis import degrade, image_generator  # noqa: PLC0415
        from ruslam.data.water import beta_rgb  # noqa: PLC0415
    except ImportError as err:
        raise ImportError(f"Turbid synthetic levels need ruslam.data.synthesis and .water ({err}).") from None
    tmp = out.with_name(out.name + f".tmp{np.random.default_rng().integers(1 << 30)}")
    cam_dirs = _write_layout(tmp, cfg, circuit_poses(cfg), level.water or "clear")
    n_cams = len(cam_dirs)
    beta = torch.as_tensor(np.asarray(beta_rgb(level.water), np.float32)).expand(n_cams, 3)
    A = torch.from_numpy(level.background_light()).expand(n_cams, 3)
    L = torch.full((n_cams,), float(level.light))
    noise = torch.full((n_cams,), float(level.noise_std))
    frames = list(enumerate(_stamps_ns(cfg)))
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        frames = tqdm(frames, desc=f"degrading ({level.water})", unit="frame")
    for i, stamp in frames:
        rgb, depth = [], []
        for c in range(n_cams):
            image = cv2.imread(str(clean / "mav0" / f"cam{c}" / "data" / f"{stamp}.png"), cv2.IMREAD_COLOR)
            rng = cv2.imread(str(clean / "mav0" / f"depth{c}" / "data" / f"{stamp}.png"), cv2.IMREAD_UNCHANGED)
            if image is None or rng is None:
                raise MissingInput(f"Clean frame {stamp} of {clean} is missing; delete {clean} to re-render.")
            rgb.append(image[..., ::-1].astype(np.float32) / 255.0)
            depth.append(rng.astype(np.float32) / DEPTH_SCALE)
        gen = [image_generator(cfg.seed, n_cams * i + c) for c in range(n_cams)]
        out_rgb = degrade(torch.from_numpy(np.stack(rgb)).permute(0, 3, 1, 2), torch.from_numpy(np.stack(depth)),
                          beta, A, L, noise, level.blur_angle_deg, level.blur_length, generator=gen)
        for c, cam_dir in enumerate(cam_dirs):
            _imwrite(cam_dir / "data" / f"{stamp}.png", out_rgb[c].permute(1, 2, 0).numpy())
    _publish(tmp, out)
    return out


def default_cache_dir() -> Path:
    return Path.home() / ".cache" / "ruslam" / "slam"


def synthetic_sequence(level: str = "clear", stereo: bool = False, cache_dir: str | Path | None = None,
                       levels: dict | None = None, progress: bool = True, **config) -> Sequence:
    """The synthetic seafloor sequence at one turbidity ``level`` (a key of ``levels``, default `LEVELS`),
    generated into ``cache_dir`` on first use and then read back with `read_euroc`."""
    levels = {**LEVELS, **{k: v if isinstance(v, WaterLevel) else WaterLevel(**v) for k, v in (levels or {}).items()}}
    if level not in levels:
        raise InputError(f"Unknown synthetic water level {level!r}; expected one of {sorted(levels)}.")
    cfg = SeafloorConfig(stereo=stereo, **{k: tuple(v) if isinstance(v, list) else v for k, v in config.items()})
    base = Path(cache_dir or default_cache_dir()) / f"seafloor_{cfg.key()}"
    base.mkdir(parents=True, exist_ok=True)
    clean = render_clean(cfg, base / "clear", progress=progress)
    spec = levels[level]
    folder = clean if spec.water is None and spec == WaterLevel() else base / f"{level}_{spec.key()}"
    if folder != clean:
        if spec.water is None:
            raise InputError(f"Synthetic level {level!r} needs a Jerlov water type (water=...).")
        degrade_level(cfg, clean, spec, folder, progress=progress)
    return read_euroc(folder, stereo=stereo, name=f"seafloor_{level}")
