"""Upatches builder: any set of images -> homography sequences in the HPatches layout (read by `HPatches`).

The paper's Upatches is 30 real underwater images (UIEB) with homography-warped copies, rotation up to 180°.
Each source image becomes a folder ``v_<id>`` with ``1.ppm`` (the source resized to ``size``), ``2.ppm`` ...
``N.ppm`` (warps of it), ``H_1_k`` and ``rotation_deg.txt`` (the sampled in-plane rotation of each pair, so results
can be binned by rotation). Two ways to sample the homographies:

- ``fit_inside=False`` (default): image k is image 1 rotated, zoomed by a factor drawn log-uniformly in
  ``zoom_range`` (0.8-1.25: around 1), with perspective jitter and a small shift. Image k may then show places
  outside image 1 (filled by replicating the edge); they are invalid, and the evaluation's shared-view filter
  drops every keypoint there, so no threshold is silently rescaled.
- ``fit_inside=True`` (the first builder): the quadrilateral image k sees lies inside image 1 (no borders). A
  rotated frame only fits inside the source when shrunk, so rotation forces a zoom-in (1.0-2.4x, median ~1.75x
  at 480x640 with ``scale_range`` 0.7-1.0 of the largest fit), and a 3 px threshold in image k is then only
  3/zoom px in image 1.

Sources: a folder of real images (`upatches_from_folder`) or, for the embedded default, procedural in-air RGB-D
scenes turned pseudo-underwater by the synthesis module (`procedural_upatches`). Building is seeded per
(seed, image index) and atomic (temp folder then rename); a finished build records its parameters in
``upatches.json`` and is reused only when they match.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import cv2
import numpy as np
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from ruslam.data.hpatches import HPatches, read_image, resize_image

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")
MANIFEST = "upatches.json"


def _frame_corners(hw: tuple[int, int]) -> np.ndarray:
    """The 4 corners of an image's extent (pixel centres at integers), clockwise from top-left."""
    h, w = hw
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]], dtype=np.float64)


def sample_homography(
    rng: np.random.Generator,
    hw: tuple[int, int],
    max_rotation_deg: float = 180.0,
    scale_range: tuple[float, float] = (0.7, 1.0),
    perspective: float = 0.1,
    max_tries: int = 100,
    fit_inside: bool = False,
    zoom_range: tuple[float, float] = (0.8, 1.25),
    max_shift: float = 0.1,
) -> tuple[np.ndarray, float]:
    """A homography image 1 -> image 2 (both of size hw) and its in-plane rotation of the content (degrees).

    Image 2 sees a quadrilateral of image 1: the frame rotated by -angle and scaled, corners jittered by up to
    ``perspective`` x half the short side (times the scale), then shifted.
    ``fit_inside``: the scale is ``scale_range`` (uniform) of the largest that fits at that angle and the shift
    keeps the quadrilateral inside image 1. Otherwise the content is zoomed by a factor drawn log-uniformly in
    ``zoom_range`` and the quadrilateral's centre is shifted by up to ``max_shift`` of the image size per axis.
    """
    h, w = hw
    angle = float(rng.uniform(-max_rotation_deg, max_rotation_deg))
    theta = np.radians(-angle)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    frame = _frame_corners(hw)
    centre = np.array([(w - 1) / 2, (h - 1) / 2])

    def homography(quad: np.ndarray) -> np.ndarray:
        H = cv2.getPerspectiveTransform(quad.astype(np.float32), frame.astype(np.float32)).astype(np.float64)
        return H / H[2, 2]

    if not fit_inside:
        lo, hi = np.log(zoom_range[0]), np.log(zoom_range[1])
        scale = 1.0 / np.exp(rng.uniform(lo, hi))  # size of the seen quadrilateral = 1 / zoom
        quad = (frame - centre) * scale @ rot.T + centre
        quad += rng.uniform(-1, 1, size=quad.shape) * perspective * scale * min(h, w) / 2
        quad += rng.uniform(-1, 1, size=2) * max_shift * np.array([w, h])
        return homography(quad), angle

    c, s = abs(np.cos(theta)), abs(np.sin(theta))
    fit = min(w / (w * c + h * s), h / (w * s + h * c))  # largest scale of the rotated frame inside image 1
    lo, hi = frame.min(0), frame.max(0)
    for attempt in range(max_tries + 1):
        jitter = perspective if attempt < max_tries else 0.0  # last resort: pure similarity, always fits
        scale = fit * rng.uniform(*scale_range)
        quad = (frame - centre) * scale @ rot.T
        quad += rng.uniform(-1, 1, size=quad.shape) * jitter * scale * min(h, w) / 2
        t_lo, t_hi = lo - quad.min(0), hi - quad.max(0)  # translations keeping quad inside image 1
        if np.all(t_lo <= t_hi):
            return homography(quad + rng.uniform(t_lo, t_hi)), angle
    raise AssertionError("unreachable: the jitter-free attempt always fits")


def warp_image(image: np.ndarray, H: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    return cv2.warpPerspective(image, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def build_upatches(
    images: Iterable[tuple[str, np.ndarray]],
    out_dir: str | Path,
    manifest: dict,
    num_warps: int = 5,
    size: tuple[int, int] = (480, 640),
    max_rotation_deg: float = 180.0,
    scale_range: tuple[float, float] = (0.7, 1.0),
    perspective: float = 0.1,
    seed: int = 0,
    fit_inside: bool = False,
    zoom_range: tuple[float, float] = (0.8, 1.25),
    max_shift: float = 0.1,
) -> Path:
    """Write one ``v_<id>`` sequence per (id, uint8 RGB image) into out_dir; reuse a finished identical build.

    ``manifest`` describes the source (folder and files, or generator parameters); it is stored together with
    the sampling parameters, and an existing out_dir built from anything else is refused.
    """
    out_dir = Path(out_dir)
    size = (int(size[0]), int(size[1]))
    manifest = {
        **manifest, "num_warps": int(num_warps), "size": list(size), "max_rotation_deg": float(max_rotation_deg),
        "perspective": float(perspective), "seed": int(seed), "fit_inside": bool(fit_inside),
    }
    if fit_inside:
        manifest["scale_range"] = [float(v) for v in scale_range]
    else:
        manifest.update(zoom_range=[float(v) for v in zoom_range], max_shift=float(max_shift))
    if fit_inside and not 0 < scale_range[0] <= scale_range[1] <= 1:
        raise ValueError(f"scale_range must satisfy 0 < low <= high <= 1 with fit_inside, got {list(scale_range)}.")
    if not fit_inside and not 0 < zoom_range[0] <= zoom_range[1]:
        raise ValueError(f"zoom_range must satisfy 0 < low <= high, got {list(zoom_range)}.")
    if out_dir.exists():
        if (out_dir / MANIFEST).is_file() and json.loads((out_dir / MANIFEST).read_text()) == manifest:
            return out_dir
        raise FileExistsError(
            f"Upatches folder {out_dir} already exists and was not built with these parameters; "
            "delete it or choose another build_dir."
        )
    tmp = out_dir.with_name(f".{out_dir.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        for index, (image_id, image) in enumerate(images):
            rng = np.random.default_rng([int(seed), index])
            reference = resize_image(np.ascontiguousarray(image), size)
            folder = tmp / f"v_{image_id}"
            folder.mkdir()
            cv2.imwrite(str(folder / "1.ppm"), cv2.cvtColor(reference, cv2.COLOR_RGB2BGR))
            rotations = []
            for k in range(2, num_warps + 2):
                H, angle = sample_homography(rng, size, max_rotation_deg, scale_range, perspective,
                                             fit_inside=fit_inside, zoom_range=zoom_range, max_shift=max_shift)
                cv2.imwrite(str(folder / f"{k}.ppm"), cv2.cvtColor(warp_image(reference, H), cv2.COLOR_RGB2BGR))
                np.savetxt(folder / f"H_1_{k}", H, fmt="%.17g")
                rotations.append(angle)
            np.savetxt(folder / "rotation_deg.txt", rotations, fmt="%.6f")
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1))
        tmp.rename(out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def _natural_key(path: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def list_folder_images(root: str | Path, num_images: int | None) -> list[Path]:
    """The first ``num_images`` image files of a folder in natural order (1, 2, ..., 10), or one clear error."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"Upatches image folder {root} is not a folder.")
    files = sorted((p for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
    if num_images is None:
        num_images = len(files)
    if num_images < 1 or len(files) < num_images:
        raise ValueError(
            f"Folder {root} holds {len(files)} image(s) ({'/'.join(IMAGE_SUFFIXES)}), "
            f"fewer than the {num_images} asked (num_images)."
        )
    return files[:num_images]


def upatches_from_folder(
    root: str | Path, build_dir: str | Path, num_images: int | None = None, eval_size=(480, 640), **sampling
) -> HPatches:
    """Build (or reuse) Upatches from a folder of real underwater images and return its reader."""
    files = list_folder_images(root, num_images)
    manifest = {"source": str(Path(root).resolve()), "files": [p.name for p in files]}
    images = ((p.stem, read_image(p)) for p in files)
    return HPatches(build_upatches(images, build_dir, manifest, **sampling), size=eval_size)


def procedural_images(
    num_images: int, height: int, width: int, seed: int, degrade: Callable | None
) -> Iterable[tuple[str, np.ndarray]]:
    """(id, uint8 RGB) of procedural in-air scenes, made pseudo-underwater by ``degrade`` (a PseudoUnderwater)."""
    import torch  # noqa: PLC0415 (only this source needs torch)

    from ruslam.data.procedural import ProceduralRGBD  # noqa: PLC0415

    scenes = ProceduralRGBD(num_images=num_images, height=height, width=width, seed=seed)
    for i in range(num_images):
        sample = scenes[i]
        rgb = sample["image"]
        if degrade is not None:
            depth = sample["depth"]
            depth = np.where(np.isfinite(depth), depth, np.nanmax(depth) if np.isfinite(depth).any() else 10.0)
            out = degrade(
                torch.from_numpy(rgb).permute(2, 0, 1)[None].float(), torch.from_numpy(depth)[None].float(), [i]
            )
            rgb = out[0].permute(1, 2, 0).detach().cpu().numpy()
        yield f"{i:03d}", np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)


def procedural_upatches(
    build_dir: str | Path,
    num_images: int = 10,
    render_size=(240, 320),
    eval_size=(480, 640),
    degrade=None,
    seed: int = 0,
    **sampling,
) -> HPatches:
    """The embedded default: Upatches from procedural scenes made pseudo-underwater by the synthesis module.

    ``degrade`` is a Hydra config of the degradation (``_target_``: PseudoUnderwater...), instantiated here so
    that the build manifest records it exactly, or a ready callable, or None for in-air images.
    """
    record = None
    if isinstance(degrade, Mapping | DictConfig):
        record = OmegaConf.to_container(OmegaConf.create(degrade), resolve=True)
        degrade = instantiate(record)
    elif degrade is not None:
        record = f"{type(degrade).__module__}.{type(degrade).__qualname__}"
    manifest = {
        "source": "procedural", "num_images": int(num_images), "render_size": [int(v) for v in render_size],
        "degrade": record,
    }
    images = procedural_images(num_images, int(render_size[0]), int(render_size[1]), seed, degrade)
    return HPatches(build_upatches(images, build_dir, manifest, seed=seed, **sampling), size=eval_size)
