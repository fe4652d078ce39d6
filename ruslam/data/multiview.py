"""The embedded default of ``task=sfm``: a rendered underwater multi-view set of a seafloor patch, known poses.

A survey over a textured seafloor with rocks (`ruslam.data.synthetic_sequence.make_seafloor`, ray-cast exactly):
``num_views`` downward-looking cameras on a jittered lawn-mower grid over the patch at 1.6-2.0 m altitude, tilted
up to ``max_tilt_deg`` towards random directions, headings within +-``max_yaw_deg`` of the survey heading, then
degraded by the pseudo-underwater model (`ruslam.data.synthesis.degrade`, paper eq. 4) for Jerlov ``water`` with
the range of every pixel. It is written as an image-folder sequence: ``<t_ns>.png`` images, ``calibration.yaml``
(pinhole, no distortion, pixel centres at integer coordinates) and ``groundtruth.txt`` (TUM, T_world_camera), into
a cache folder named by the hash of its configuration, so later runs reuse it.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

VERSION = 2  # bump when rendering changes, so stale caches are regenerated


@dataclass(frozen=True)
class MultiViewConfig:
    num_views: int = 24
    width: int = 640
    height: int = 480
    focal: float = 450.0
    spacing: float = 0.45  # metres between neighbouring grid positions (about 75 % overlap at 1.8 m)
    altitude: tuple[float, float] = (1.6, 2.0)
    max_tilt_deg: float = 15.0
    max_yaw_deg: float = 20.0
    water: str = "5C"  # Jerlov type of the degradation; "clear" keeps the in-air render
    noise_std: float = 0.01
    blur_length: float = 3.0
    seed: int = 0

    def key(self) -> str:
        text = json.dumps({**asdict(self), "version": VERSION}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:10]


def default_cache_dir() -> Path:
    return Path(os.environ.get("RUSLAM_CACHE", Path.home() / ".cache" / "ruslam")) / "sfm"


def survey_poses(cfg: MultiViewConfig) -> np.ndarray:
    """T_world_cam [V, 4, 4] of the survey (world z up, camera OpenCV: x right, y down, z forward)."""
    rng = np.random.default_rng(cfg.seed)
    cols = int(np.ceil(np.sqrt(cfg.num_views * 4 / 3)))
    rows = int(np.ceil(cfg.num_views / cols))
    poses = []
    for i in range(cfg.num_views):
        r, c = divmod(i, cols)
        c = c if r % 2 == 0 else cols - 1 - c  # lawn-mower order
        xy = (np.array([c - (cols - 1) / 2, r - (rows - 1) / 2]) * cfg.spacing
              + rng.uniform(-0.25, 0.25, 2) * cfg.spacing)
        z = rng.uniform(*cfg.altitude)
        yaw = np.deg2rad(rng.uniform(-cfg.max_yaw_deg, cfg.max_yaw_deg))
        tilt = np.deg2rad(rng.uniform(0, cfg.max_tilt_deg))
        tilt_dir = rng.uniform(0, 2 * np.pi)
        # looking straight down with image "up" towards +y (the survey heading), then heading and tilt
        R_down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
        R = (Rotation.from_rotvec([0, 0, yaw]).as_matrix()
             @ Rotation.from_rotvec(tilt * np.array([np.cos(tilt_dir), np.sin(tilt_dir), 0])).as_matrix() @ R_down)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, [xy[0], xy[1], z]
        poses.append(T)
    return np.stack(poses)


def _stamps(n: int) -> list[int]:
    # 1 Hz, named <t_ns>.png as the image-folder sequences (epoch-like stamps: same digit count, name order = time
    # order, and large enough to read as nanoseconds)
    return [1_600_000_000_000_000_000 + 1_000_000_000 * i for i in range(n)]


def render_multiview(cfg: MultiViewConfig | None = None, cache_dir: str | Path | None = None,
                     progress: bool = False) -> Path:
    """The folder of the rendered set (rendered on first use; about a second per view)."""
    cfg = cfg or MultiViewConfig()
    out = Path(cache_dir or default_cache_dir()) / f"multiview_{cfg.key()}"
    if (out / "groundtruth.txt").is_file():
        return out
    from ruslam.data.camera import Camera  # noqa: PLC0415
    from ruslam.data.synthetic_sequence import (  # noqa: PLC0415
        SeafloorConfig,
        make_seafloor,
        pixel_rays,
        render,
        texture_pyramid,
    )

    floor_cfg = SeafloorConfig(half_extent=4.0, height_res=800, texture_res=2560, num_rocks=30, seed=cfg.seed)
    floor = make_seafloor(floor_cfg, num_pebbles=4700)
    levels = texture_pyramid(floor.texture)
    camera = Camera(cfg.width, cfg.height, cfg.focal, cfg.focal, (cfg.width - 1) / 2, (cfg.height - 1) / 2)
    rays = pixel_rays(camera)
    poses = survey_poses(cfg)
    stamps = _stamps(cfg.num_views)
    tmp = out.with_name(out.name + f".tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    views = range(cfg.num_views)
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        views = tqdm(views, desc="rendering views", unit="view")
    for i in views:
        rgb, rng = render(floor, rays, poses[i], texture_levels=levels)
        rgb = _degrade(rgb, rng, cfg, i) if cfg.water != "clear" else rgb
        image = np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8)[..., ::-1]
        cv2.imwrite(str(tmp / f"{stamps[i]}.png"), image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    (tmp / "calibration.yaml").write_text(
        f"model: pinhole\nwidth: {cfg.width}\nheight: {cfg.height}\n"
        f"intrinsics: [{cfg.focal}, {cfg.focal}, {camera.cx}, {camera.cy}]\ndistortion: [0, 0, 0, 0]\nfps: 1\n")
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    rows = [f"{t * 1e-9:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {x:.12f} {y:.12f} {z:.12f} {w:.12f}"
            for t, p, (x, y, z, w) in zip(stamps, poses[:, :3, 3], q, strict=True)]
    (tmp / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw (T_world_camera)\n" + "\n".join(rows) + "\n")
    (tmp / "README.md").write_text(f"Rendered underwater multi-view set (ruslam.data.multiview): {asdict(cfg)}\n")
    shutil.rmtree(out, ignore_errors=True)
    os.replace(tmp, out)
    return out


def _degrade(rgb: np.ndarray, rng: np.ndarray, cfg: MultiViewConfig, index: int) -> np.ndarray:
    import torch  # noqa: PLC0415

    from ruslam.data.synthesis import degrade, image_generator  # noqa: PLC0415
    from ruslam.data.synthetic_sequence import WaterLevel  # noqa: PLC0415

    level = WaterLevel(cfg.water, noise_std=cfg.noise_std, blur_length=cfg.blur_length)
    from ruslam.data.water import beta_rgb  # noqa: PLC0415

    out = degrade(torch.from_numpy(rgb).permute(2, 0, 1)[None], torch.from_numpy(rng)[None],
                  torch.as_tensor(np.asarray(beta_rgb(cfg.water), np.float32))[None],
                  torch.from_numpy(level.background_light())[None], torch.ones(1), torch.full((1,), cfg.noise_std),
                  level.blur_angle_deg, cfg.blur_length, generator=[image_generator(cfg.seed, index)])
    return out[0].permute(1, 2, 0).numpy()
