"""Embedded in-air RGB-D source: ray-cast textured rooms with exact metric depth (no download needed).

Each scene is a room (an axis-aligned box seen from inside: floor, ceiling, four walls) holding boxes (yawed about
the vertical), spheres and bumpy height-field patches on the floor, textured from a bank of corner- and blob-rich
textures (`procedural_textures`) and ray-cast by `procedural_render` (vectorised numpy, no per-pixel Python;
240x320 costs ~50 ms CPU, `bench/procedural.py`).  Shading is two-sided Lambertian under one directional light
plus ambient.  ``depth`` is the z-depth (distance along the optical axis); camera and world conventions are those
of `procedural_render` (OpenCV camera axes, world z up, floor z = 0).  Scenes are deterministic per (seed,
index): the generator is ``np.random.default_rng([seed, index])``.

`Scene`, `render`, `intrinsics`, `look_pose` and `jitter_pose` are re-exported here for custom trajectories.
"""

from __future__ import annotations

import cv2
import numpy as np

from ruslam.data.procedural_render import Scene, intrinsics, jitter_pose, look_pose, render
from ruslam.data.procedural_textures import TEXTURE_SIZE, texture_bank
from ruslam.errors import InputError

__all__ = ["ProceduralRGBD", "Scene", "intrinsics", "jitter_pose", "look_pose", "random_scene", "render"]


def random_scene(rng: np.random.Generator, hfov_deg: float = 60.0, num_textures: int = 48) -> Scene:
    """A room of 6-10 m by 6-10 m with 3-8 boxes, 1-4 spheres and 0-2 bumpy height-field patches, most placed
    inside the reference camera's view at 2-8 m, the camera at least 0.4 m from every object (so jittered views
    stay outside them).

    Measured over 64 scenes: z-depth percentiles 1/50/99 = 1.2/2.8/8.1 m, max 9.4 m: far enough for the Jerlov
    attenuation of the synthesis to vary strongly across an image."""
    hx, hy, height = rng.uniform(3.0, 5.0), rng.uniform(3.0, 5.0), rng.uniform(2.6, 4.0)
    cam = np.array([rng.uniform(-hx + 0.7, hx - 0.7), rng.uniform(-hy + 0.7, hy - 0.7), rng.uniform(0.8, 2.0)])
    yaw = np.arctan2(-cam[1], -cam[0]) + rng.uniform(-0.9, 0.9)  # roughly towards the room centre
    pose = look_pose(cam, yaw, np.radians(rng.uniform(-25, -3)), np.radians(rng.uniform(-8, 8)))

    def place(radius: float, z: float) -> np.ndarray | None:
        for _ in range(20):
            if rng.random() < 0.8:  # in front of the camera, within the horizontal field of view
                bearing = yaw + rng.uniform(-0.6, 0.6) * np.radians(hfov_deg)
                xy = cam[:2] + rng.uniform(2.0, 8.0) * np.array([np.cos(bearing), np.sin(bearing)])
            else:
                xy = rng.uniform([-hx, -hy], [hx, hy])
            centre = np.array([xy[0], xy[1], z])
            inside = abs(xy[0]) < hx - radius and abs(xy[1]) < hy - radius
            if inside and np.linalg.norm(centre - cam) > radius + 0.4:
                return centre
        return None

    centers, halves, yaws = [np.array([0.0, 0.0, height / 2])], [np.array([hx, hy, height / 2])], [0.0]
    for _ in range(rng.integers(3, 9)):
        half = rng.uniform([0.15, 0.15, 0.15], [0.8, 0.8, 1.0])
        z = half[2] if rng.random() < 0.75 else rng.uniform(half[2], height - half[2])
        c = place(float(np.linalg.norm(half)), z)
        if c is not None:
            centers.append(c), halves.append(half), yaws.append(rng.uniform(0, np.pi / 2))
    sph_c, sph_r = [], []
    for _ in range(rng.integers(1, 5)):
        r = rng.uniform(0.2, 0.7)
        c = place(r, r if rng.random() < 0.6 else rng.uniform(r, height - r))
        if c is not None:
            sph_c.append(c), sph_r.append(r)
    n_box, n_sph = len(centers), len(sph_c)
    box_tex = rng.integers(0, num_textures, (n_box, 6))
    same = rng.random(n_box) < 0.5
    box_tex[same] = box_tex[same, :1]
    size_m = np.concatenate([rng.uniform(1.0, 2.5, 1), rng.uniform(0.4, 1.5, n_box - 1 + n_sph)])
    light = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.8, 2.0)])
    sph_tex = rng.integers(0, num_textures, n_sph)
    n = n_box + n_sph
    uv_angle, uv_offset = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, TEXTURE_SIZE, (n, 2))
    tint, ambient = rng.uniform(0.85, 1.1, (n, 3)), float(rng.uniform(0.5, 0.7))
    # Height-fields come last in the random stream: adding them left every box, sphere and camera unchanged.
    fld_c, fld_h, fld_z = [], [], []
    for _ in range(rng.integers(0, 3)):
        half = rng.uniform(1.0, 2.5, 2)
        c = place(float(np.linalg.norm(half)), 0.0)
        if c is not None:
            u = np.sin(np.linspace(0, np.pi, 17))
            bumps = cv2.resize(rng.random((5, 5)), (17, 17), interpolation=cv2.INTER_CUBIC)
            fld_c.append(c[:2]), fld_h.append(half)
            fld_z.append(rng.uniform(0.2, 0.8) * np.clip(bumps, 0, 1) * np.sqrt(np.outer(u, u)))
    n_fld = len(fld_c)
    return Scene(
        box_center=np.array(centers), box_half=np.array(halves), box_yaw=np.array(yaws),
        box_texture=box_tex,
        sphere_center=np.array(sph_c).reshape(n_sph, 3), sphere_radius=np.array(sph_r), sphere_texture=sph_tex,
        texel_density=TEXTURE_SIZE / np.concatenate([size_m, rng.uniform(0.8, 2.0, n_fld)]),
        uv_angle=np.concatenate([uv_angle, rng.uniform(0, 2 * np.pi, n_fld)]),
        uv_offset=np.concatenate([uv_offset, rng.uniform(0, TEXTURE_SIZE, (n_fld, 2))]),
        tint=np.concatenate([tint, rng.uniform(0.85, 1.1, (n_fld, 3))]),
        light_dir=light / np.linalg.norm(light), ambient=ambient, T_world_cam=pose,
        field_center=np.array(fld_c).reshape(n_fld, 2), field_half=np.array(fld_h).reshape(n_fld, 2),
        field_heights=np.array(fld_z).reshape(n_fld, 17, 17), field_texture=rng.integers(0, num_textures, n_fld),
    )


class ProceduralRGBD:
    """Map-style in-air RGB-D dataset of ``num_images`` procedural scenes (the embedded default ``data=``).

    ``ds[i]`` -> ``{"id", "image" float32 HxWx3 [0,1], "depth" float32 HxW z-depth metres}``; scene ``i`` is the
    same for every resolution.  For "same scene, small camera motion" views use
    ``render_view(i, camera_jitter=(rot_deg, trans_m), jitter_seed=j)``; ``scene(i)`` and ``K`` give the raw
    pieces (``scene(i).render(T_world_cam, ds.K, h, w, ds.textures)``) for custom trajectories.
    """

    def __init__(self, num_images: int, height: int = 240, width: int = 320, seed: int = 0,
                 hfov_deg: float = 60.0, num_textures: int = 48):
        if num_images < 1 or height < 16 or width < 16:
            raise InputError(f"ProceduralRGBD needs num_images >= 1 and an image of at least 16x16 pixels, got "
                             f"num_images={num_images}, height={height}, width={width}.")
        if not 10.0 <= hfov_deg <= 150.0:
            raise InputError(f"hfov_deg must lie in [10, 150] degrees, got {hfov_deg}.")
        self.num_images, self.height, self.width, self.seed = int(num_images), int(height), int(width), int(seed)
        self.hfov_deg, self.num_textures = float(hfov_deg), int(num_textures)
        self.K = intrinsics(self.height, self.width, self.hfov_deg)

    @property
    def textures(self) -> tuple[np.ndarray, ...]:
        return texture_bank(self.seed, self.num_textures)

    def __len__(self) -> int:
        return self.num_images

    def _check(self, index: int) -> int:
        if not -self.num_images <= index < self.num_images:
            raise IndexError(f"Procedural image index {index} is out of range for {self.num_images} images.")
        return index % self.num_images

    def scene(self, index: int) -> Scene:
        return random_scene(np.random.default_rng([self.seed, self._check(index)]), self.hfov_deg,
                            self.num_textures)

    def image_id(self, index: int) -> str:
        return f"procedural-s{self.seed}-{self._check(index):06d}"

    def __getitem__(self, index: int) -> dict:
        scene = self.scene(index)
        image, depth = render(scene, scene.T_world_cam, self.K, self.height, self.width, self.textures)
        return {"id": self.image_id(index), "image": image, "depth": depth}

    def render_view(self, index: int, camera_jitter: tuple[float, float] = (0.0, 0.0), jitter_seed: int = 0) -> dict:
        """The scene of ``index`` seen from its camera rotated by ``camera_jitter[0]`` degrees about a random axis
        and moved ``camera_jitter[1]`` metres in a random direction (random draws seeded by (seed, index,
        jitter_seed)).  Adds ``K`` and ``T_world_cam`` to the sample."""
        scene = self.scene(index)
        rng = np.random.default_rng([self.seed, self._check(index), int(jitter_seed), 1])
        pose = jitter_pose(scene.T_world_cam, float(camera_jitter[0]), float(camera_jitter[1]), rng)
        image, depth = render(scene, pose, self.K, self.height, self.width, self.textures)
        return {"id": f"{self.image_id(index)}-j{jitter_seed}", "image": image, "depth": depth,
                "K": self.K.copy(), "T_world_cam": pose}
