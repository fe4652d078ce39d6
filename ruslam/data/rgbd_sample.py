"""The RGB-D sample contract shared by every in-air source, and its one validation door.

A sample is ``{"id": str, "image": float32 HxWx3 RGB in [0, 1], "depth": float32 HxW metres}``.  Sensors mark
missing depth differently (0 in Kinect/TUM PNGs, NaN or inf after conversions, negative after bad scaling), so
every source passes its arrays through `make_sample`, which turns all of those into NaN: downstream code (the
synthesis, the teachers) then needs to know only one invalid marker.
"""

from __future__ import annotations

import numpy as np

from ruslam.errors import InputError


def sample_image(item: dict) -> np.ndarray:
    """The image of a sample, or one sentence naming the sample when it is not a finite HxWx3 array."""
    image = item.get("image")
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or not np.isfinite(image).all():
        shape = getattr(image, "shape", type(image).__name__)
        raise InputError(f"Image {item.get('id')!r} is unreadable: expected a finite HxWx3 array, got {shape}.")
    return image


def make_sample(image_id: str, image: np.ndarray, depth: np.ndarray, source: str = "") -> dict:
    """Validate and normalise one sample; ``source`` (a file name) is named in error messages."""
    where = f" ({source})" if source else ""
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"Colour image of sample {image_id!r}{where} must be HxWx3 RGB, got shape {image.shape}.")
    if image.dtype == np.uint8:
        image = image.astype(np.float32) / np.float32(255.0)
    elif np.issubdtype(image.dtype, np.floating):
        if not (np.nanmin(image) >= -1e-3 and np.nanmax(image) <= 1.0 + 1e-3):
            raise InputError(f"Float colour image of sample {image_id!r}{where} must lie in [0, 1], got values in "
                             f"[{np.nanmin(image):.3g}, {np.nanmax(image):.3g}].")
        image = np.clip(image.astype(np.float32), 0.0, 1.0)
    else:
        raise InputError(f"Colour image of sample {image_id!r}{where} must be 8-bit RGB, got dtype {image.dtype}.")
    if depth.ndim != 2:
        raise InputError(f"Depth of sample {image_id!r}{where} must be a 2-D HxW map, got shape {depth.shape}.")
    if depth.shape != image.shape[:2]:
        raise InputError(f"Depth of sample {image_id!r}{where} is {depth.shape[0]}x{depth.shape[1]} but its colour "
                         f"image is {image.shape[0]}x{image.shape[1]}; they must have the same size.")
    depth = depth.astype(np.float32)  # a copy: the caller's array is never modified
    depth[~(np.isfinite(depth) & (depth > 0))] = np.nan
    if np.isnan(depth).all():
        raise InputError(f"Depth of sample {image_id!r}{where} has no valid pixel (all 0, negative, NaN or inf).")
    return {"id": image_id, "image": image, "depth": depth}
