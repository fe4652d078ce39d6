"""Sequences of the robustness matrix: laps of a rounded rectangle over the synthetic seafloor, one knob per
condition the SLAM must survive (how far and how fast the camera moves and turns per frame, how it looks at the
floor, how textured the floor is, the water).

Motion is set per frame (``step`` x altitude, ``turn_deg`` in the corners); ``fps`` only sets the timestamps, so a
vehicle filmed at 20 Hz instead of 10 Hz is the same path with half the step and half the turn per frame. The
corners are arcs of radius ``step / turn``: the heading changes by exactly ``turn_deg`` per frame there, and the
straights are given in frames, so the cost of a lap is known in advance (``2 (long + short) + 360 / turn_deg``
frames). ``laps > 1`` flies over the start again, so loop closure can happen.

Each variant is rendered once at its own resolution (ray-cast with mip-mapped texture, water applied in the same
pass by eq. 4 of the pseudo-underwater model) into ``~/.cache/ruslam/robustness/<name>_<hash of the knobs>`` in the
EuRoC layout, then read back with `read_euroc`. The grid itself (DEV for tuning, TEST for reporting) is
``conf/dataset/robustness.yaml``.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ruslam.data.camera import Camera
from ruslam.data.readers import Sequence, read_euroc
from ruslam.data.synthetic_sequence import (
    SeafloorConfig,
    WaterLevel,
    _imwrite,
    _publish,
    _stamps_ns,
    _write_layout,
    downward_poses,
    make_seafloor,
    pixel_rays,
    render,
    texture_pyramid,
)
from ruslam.data.tiled_pool import make_pool, render_pool
from ruslam.errors import InputError

VERSION = 1  # bump when rendering changes, so stale caches are regenerated
MAX_INCIDENCE_DEG = 85.0  # rays nearer the horizon see open water (background light), not the floor


@dataclass(frozen=True)
class SurveyConfig:
    """Every knob of one robustness sequence; its hash names the cache folder."""

    # path
    altitude: float = 2.0  # metres above the mean seafloor
    step: float = 0.10  # distance flown per frame / altitude
    turn_deg: float = 6.0  # heading change per frame in the corners
    straights: tuple[int, int] = (12, 6)  # frames along the long and the short sides of the rectangle
    laps: float = 1.2  # > 1: the end flies over the start again
    frames: int | None = None  # number of frames; None: laps x frames per lap
    pitch_deg: float = 30.0  # forward tilt of the camera from straight down, 0-60 (pool: 0-80)
    fps: float = 10.0  # timestamps only (the motion per frame is step and turn_deg)
    # camera
    width: int = 320
    height: int = 240
    hfov_deg: float = 70.8  # horizontal field of view (the embedded sequence's 640 px at f = 450)
    k1: float = 0.0  # radial lens distortion (k1 of radial-tangential, k2 = -k1 / 2: barrel for k1 < 0)
    stereo: bool = False
    baseline: float = 0.12  # metres, right camera along +x of the left one
    # scene: "seafloor" (rocks and sand) or "pool" (a tiled floor and walls, ruslam.data.tiled_pool)
    scene: str = "seafloor"
    tile_m: float = 0.05  # pool: tile size in metres
    # seafloor
    contrast: float = 1.0  # albedo deviations from the mean colour x this (0.3 = washed-out sand)
    density: float = 1.0  # rocks and pebbles per unit area x this (0.2 = sparse)
    # water (eq. 4); water=None renders in air
    water: str | None = "I"  # Jerlov type: I (clearest ocean) ... 9C (most turbid coastal)
    light: float = 1.0  # extra illumination factor L
    noise_std: float = 0.01  # sensor noise (std, image in [0, 1])
    blur_px: float = 2.0  # motion-blur length in pixels (direct light only)
    seed: int = 0

    def __post_init__(self):
        max_pitch = 80 if self.scene == "pool" else 60  # a seafloor ray-cast needs every ray pointing down
        checks = [(self.scene in ("seafloor", "pool"), f"scene must be 'seafloor' or 'pool', got {self.scene!r}"),
                  (0 <= self.pitch_deg <= max_pitch, f"pitch_deg must be within 0-{max_pitch}, got {self.pitch_deg}"),
                  (self.tile_m > 0, f"tile_m must be > 0, got {self.tile_m}"),
                  (self.altitude > 0 and self.step > 0,
                   f"altitude and step must be > 0, got {self.altitude} and {self.step}"),
                  (0 < self.turn_deg <= 45, f"turn_deg must be within (0, 45] degrees per frame, got {self.turn_deg}"),
                  (min(self.straights) >= 0 and len(self.straights) == 2,
                   f"straights must be two frame counts >= 0, got {self.straights}"),
                  (self.laps > 0 and (self.frames is None or self.frames >= 2),
                   f"laps must be > 0 and frames >= 2, got {self.laps} and {self.frames}"),
                  (self.contrast > 0 and self.density >= 0,
                   f"contrast must be > 0 and density >= 0, got {self.contrast} and {self.density}"),
                  (self.width >= 32 and self.height >= 32 and 10 < self.hfov_deg < 150,
                   f"the camera must be at least 32x32 px with a field of view within (10, 150) degrees, got "
                   f"{self.width}x{self.height} px and {self.hfov_deg}"),
                  (self.fps > 0, f"fps must be > 0, got {self.fps}")]
        for ok, what in checks:
            if not ok:
                raise InputError(f"Robustness sequence: {what}.")
        if self.water is not None:
            from ruslam.data.water import check_water_type  # noqa: PLC0415

            check_water_type(self.water)

    # --- derived quantities --------------------------------------------------------------------------------
    @property
    def step_m(self) -> float:
        return self.step * self.altitude

    @property
    def corner_radius(self) -> float:
        return self.step_m / np.deg2rad(self.turn_deg)

    @property
    def lap_frames(self) -> float:
        return 2 * sum(self.straights) + 360.0 / self.turn_deg

    @property
    def num_frames(self) -> int:
        return int(self.frames) if self.frames is not None else max(2, int(round(self.laps * self.lap_frames)))

    @property
    def revisits(self) -> bool:
        """True when the path flies over its start again (a loop can be closed)."""
        return self.num_frames > self.lap_frames + 5

    def camera(self) -> Camera:
        f = float((self.width / 2) / np.tan(np.deg2rad(self.hfov_deg) / 2))
        return Camera(self.width, self.height, f, f, (self.width - 1) / 2, (self.height - 1) / 2,
                      dist=[self.k1, -self.k1 / 2, 0.0, 0.0])

    def key(self) -> str:
        defaults = {"k1": 0.0, "scene": "seafloor", "tile_m": 0.05}  # later knobs at their default: keys as before
        knobs = {k: v for k, v in asdict(self).items() if not (k in defaults and v == defaults[k])}
        text = json.dumps({**knobs, "version": VERSION}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:10]


# ---------------------------------------------------------------------------------------------------- the path


def _lap_point(cfg: SurveyConfig, u: float) -> tuple[float, float, float]:
    """(x, y, heading) at arc length u along one lap (counter-clockwise, starting at the long bottom straight)."""
    a, b = cfg.straights[0] * cfg.step_m, cfg.straights[1] * cfg.step_m
    r = cfg.corner_radius
    u = u % (2 * (a + b) + 2 * np.pi * r)
    x, y, heading = -a / 2, -b / 2 - r, 0.0
    for length in (a, b, a, b):
        c, s = np.cos(heading), np.sin(heading)
        if u <= length:  # along the straight
            return x + u * c, y + u * s, heading
        x, y, u = x + length * c, y + length * s, u - length
        centre = (x - r * s, y + r * c)  # the corner turns left about this centre
        arc = min(u / r, np.pi / 2)
        px, py = centre[0] + r * np.sin(heading + arc), centre[1] - r * np.cos(heading + arc)
        if u <= r * np.pi / 2:
            return px, py, heading + arc
        x, y, heading, u = px, py, heading + np.pi / 2, u - r * np.pi / 2
    return x, y, heading  # unreachable: u is reduced modulo the lap length


def survey_poses(cfg: SurveyConfig) -> np.ndarray:
    """T_world_cam0 [N, 4, 4]: heading along the path, optical axis pitched forward from straight down."""
    n = cfg.num_frames
    points = np.array([_lap_point(cfg, i * cfg.step_m) for i in range(n)])
    phase = np.arange(n) * cfg.step_m / cfg.altitude
    pos = np.column_stack([points[:, :2], cfg.altitude * (1 + 0.03 * np.sin(0.7 * phase))])  # gentle heave
    fwd = np.column_stack([np.cos(points[:, 2]), np.sin(points[:, 2]), np.zeros(n)])
    return downward_poses(pos, fwd, cfg.pitch_deg, np.deg2rad(1.5) * np.sin(1.3 * phase))


# ------------------------------------------------------------------------------------------------ the seafloor


def survey_seafloor(cfg: SurveyConfig, poses: np.ndarray):
    """A seafloor that covers the path plus what the camera sees ahead, with texel ~ 2/3 of a nadir pixel."""
    reach = cfg.altitude * (1 + np.tan(np.deg2rad(min(cfg.pitch_deg + 15, 75))))
    half = float(np.abs(poses[:, :2, 3]).max() + reach + 1.0)
    pixel_m = cfg.altitude / cfg.camera().fx
    texture_res = int(min(4096, 2 ** np.ceil(np.log2(2 * half / (pixel_m / 1.5)))))
    area = (2 * half) ** 2 / 13.0**2  # relative to the embedded 13 m square (70 rocks)
    floor_cfg = SeafloorConfig(half_extent=half, height_res=int(2 * half / 0.02), texture_res=texture_res,
                               num_rocks=int(round(70 * area * cfg.density)), seed=cfg.seed)
    floor = make_seafloor(floor_cfg, num_pebbles=int(round(12000 * cfg.density * (texture_res / 4096) ** 2 * 4)))
    if cfg.contrast != 1.0:
        tex = floor.texture.astype(np.float32)
        mean = tex.reshape(-1, 3).mean(axis=0)
        floor.texture = np.clip(mean + cfg.contrast * (tex - mean) + 0.5, 0, 255).astype(np.uint8)
    return floor


# -------------------------------------------------------------------------------------------------- rendering


def _apply_water(cfg: SurveyConfig, rgbs: list[np.ndarray], ranges: list[np.ndarray], index: int) -> list:
    """Eq. 4 (``ruslam.data.synthesis.degrade``) on one frame's images; in air only the sensor noise."""
    import torch  # noqa: PLC0415

    from ruslam.data.synthesis import degrade, image_generator  # noqa: PLC0415
    from ruslam.data.water import beta_rgb  # noqa: PLC0415

    n = len(rgbs)
    gens = [image_generator(cfg.seed, n * index + c) for c in range(n)]
    if cfg.water is None:
        return [np.clip(cfg.light * rgb + cfg.noise_std * torch.randn(rgb.shape, generator=g).numpy(), 0, 1)
                for rgb, g in zip(rgbs, gens, strict=True)]
    level = WaterLevel(cfg.water, light=cfg.light, noise_std=cfg.noise_std, blur_length=cfg.blur_px)
    beta = torch.as_tensor(np.asarray(beta_rgb(cfg.water), np.float32)).expand(n, 3)
    A = torch.from_numpy(level.background_light()).expand(n, 3)
    out = degrade(torch.from_numpy(np.stack(rgbs)).permute(0, 3, 1, 2), torch.from_numpy(np.stack(ranges)), beta, A,
                  torch.full((n,), cfg.light), torch.full((n,), cfg.noise_std), level.blur_angle_deg, cfg.blur_px,
                  generator=gens)
    return [im.permute(1, 2, 0).numpy() for im in out]


def render_survey(cfg: SurveyConfig, out: Path, progress: bool = False) -> Path:
    """Render the whole sequence into ``out`` (EuRoC layout, ground truth included); a no-op when it exists."""
    if out.is_dir():
        return out
    tmp = out.with_name(out.name + f".tmp{os.getpid()}_{np.random.default_rng().integers(1 << 30)}")
    poses = survey_poses(cfg)
    if cfg.scene == "pool":
        pool = make_pool(poses[:, :2, 3], cfg.tile_m, cfg.seed)
        view = partial(render_pool, pool)
    else:
        floor = survey_seafloor(cfg, poses)
        view = partial(render, floor, texture_levels=texture_pyramid(floor.texture),
                       max_incidence_deg=MAX_INCIDENCE_DEG)
    cam_dirs = _write_layout(tmp, cfg, poses, cfg.water or "air")
    rays = pixel_rays(cfg.camera())
    offsets = [np.eye(4)]
    if cfg.stereo:
        offsets.append(np.eye(4))
        offsets[1][0, 3] = cfg.baseline
    stamps = _stamps_ns(cfg)
    frames = range(cfg.num_frames)
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        frames = tqdm(frames, desc=f"rendering {out.name}", unit="frame")
    for i in frames:
        views = [view(rays, poses[i] @ T) for T in offsets]
        images = _apply_water(cfg, [v[0] for v in views], [v[1] for v in views], i)
        for cam_dir, image in zip(cam_dirs, images, strict=True):
            _imwrite(cam_dir / "data" / f"{stamps[i]}.png", image)
    _publish(tmp, out)
    return out


def default_cache_dir() -> Path:
    return Path(os.environ.get("RUSLAM_CACHE", Path.home() / ".cache" / "ruslam")) / "robustness"


def robustness_sequence(name: str = "survey", cache_dir: str | Path | None = None, progress: bool = True,
                        dropped=(), **knobs) -> Sequence:
    """The sequence of one variant (``knobs``: fields of `SurveyConfig`), rendered on first use. ``dropped``:
    [start, stop) frame ranges left out (a camera that drops frames: the kept neighbours are far apart, the
    ground truth stays whole)."""
    unknown = sorted(set(knobs) - set(SurveyConfig.__dataclass_fields__))
    if unknown:
        raise InputError(f"Robustness variant {name!r}: unknown knob(s) {unknown}; expected fields of "
                         f"SurveyConfig: {sorted(SurveyConfig.__dataclass_fields__)}.")
    as_tuple = {k: tuple(v) for k, v in knobs.items() if not isinstance(v, str) and hasattr(v, "__len__")}
    cfg = SurveyConfig(**{**knobs, **as_tuple})  # lists from YAML -> tuples (hashable, same cache key)
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    root.mkdir(parents=True, exist_ok=True)
    folder = render_survey(cfg, root / f"{name}_{cfg.key()}", progress=progress)
    seq = read_euroc(folder, stereo=cfg.stereo, name=name)
    drop = {i for start, stop in dropped for i in range(int(start), int(stop))}
    if not drop:
        return seq
    if not drop < set(range(len(seq))):
        raise InputError(f"Robustness variant {name!r}: dropped frames {sorted(drop)} must lie within 0-{len(seq) - 1} "
                         "and leave frames.")
    return seq.subset(i for i in range(len(seq)) if i not in drop)
