"""Extraction, pairing and matching that write hloc's files (`ruslam.features.hloc_io`), with progress bars.

`extract_features(images, out, extractor)` -> features.h5; `make_pairs(...)` -> pairs (exhaustive, a sequential
window, retrieval by the extractor's global descriptor, or a union); `match_features(features, pairs, out)` ->
matches.h5 (mutual nearest neighbours with an optional ratio test, or LightGlue). Every file is written to a
temporary name and renamed when complete (`ruslam.atomic_files`).
"""

from __future__ import annotations

import re
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import h5py
import numpy as np
from tqdm import tqdm

from ruslam.atomic_files import atomic_path
from ruslam.data.readers import load_image
from ruslam.errors import InputError, MissingInput
from ruslam.features.hloc_io import (
    list_feature_names,
    open_h5,
    read_features,
    write_feature_group,
    write_matches_group,
)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


def list_images(root: str | Path, every: int = 1) -> list[str]:
    """Image paths relative to ``root`` (sub-folders included, hloc's names), sorted; every ``every``-th one."""
    root = Path(root)
    if not root.is_dir():
        raise MissingInput(f"Image folder {root} does not exist.")
    if int(every) < 1:
        raise InputError(f"every must be a positive integer, got {every!r}.")
    names = sorted((p.relative_to(root).as_posix() for p in root.rglob("*")
                    if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file() and not p.name.startswith(".")),
                   key=_natural_key)
    if not names:
        raise InputError(f"Image folder {root} holds no images ({', '.join(IMAGE_SUFFIXES)}).")
    return names[::int(every)]


def _natural_key(name: str) -> list:
    """Name order with numbers compared as numbers (frame 9 before frame 10)."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name)]


def resize_longer(image: np.ndarray, resize_max: int | None) -> tuple[np.ndarray, float]:
    """The image shrunk so its longer side is at most ``resize_max`` (None: unchanged), and the scale applied."""
    h, w = image.shape[:2]
    if not resize_max or max(h, w) <= resize_max:
        return image, 1.0
    scale = resize_max / max(h, w)
    size = (max(16, round(w * scale)), max(16, round(h * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale


def extract_features(image_dir: str | Path, out_path: str | Path, extractor, names: Sequence[str] | None = None,
                     resize_max: int | None = None, half: bool = True, progress: bool = True) -> dict:
    """Run ``extractor`` (a name for `load_extractor`, or an `Extractor`) on every image of ``image_dir`` (or the
    listed ``names``) and write hloc's features.h5 to ``out_path``. Returns {"images", "keypoints", "seconds"}.

    ``resize_max`` shrinks images whose longer side exceeds it before extraction (hloc's ``resize_max``);
    keypoints are mapped back to the original pixels with ``(x + 0.5) / s - 0.5``. The extractor's own working size
    applies after that."""
    image_dir = Path(image_dir)
    names = list(names) if names is not None else list_images(image_dir)
    if not names:
        raise InputError(f"No images to extract in {image_dir}.")
    for name in names:  # every file named must exist before any work starts
        if not (image_dir / name).is_file():
            raise MissingInput(f"Image {image_dir / name} does not exist.")
    if resize_max is not None and not (isinstance(resize_max, int) and resize_max >= 16):
        raise InputError(f"resize_max must be an integer of at least 16 pixels, got {resize_max!r}.")
    if isinstance(extractor, str | Path):
        from ruslam.models.registry import load_extractor  # noqa: PLC0415 (torch only when needed)

        extractor = load_extractor(extractor)
    total, start = 0, time.perf_counter()
    with atomic_path(out_path) as tmp, h5py.File(tmp, "w", libver="latest") as fd:
        for name in tqdm(names, desc="extracting", unit="image", disable=not progress):
            image = load_image(image_dir / name)
            h, w = image.shape[:2]
            small, scale = resize_longer(image, resize_max)
            pred = extractor.extract(small)
            if scale != 1.0:
                sh, sw = small.shape[:2]
                pred["keypoints"] = ((pred["keypoints"] + 0.5) * np.array([w / sw, h / sh], np.float32) - 0.5)
            write_feature_group(fd, name, pred, (w, h), half=half)
            total += len(pred["keypoints"])
    return {"images": len(names), "keypoints": total, "seconds": time.perf_counter() - start}


# ------------------------------------------------------------------------------------------------------ pairs


def pairs_exhaustive(names: Sequence[str]) -> list[tuple[str, str]]:
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]


def pairs_sequential(names: Sequence[str], window: int) -> list[tuple[str, str]]:
    """Each image with the next ``window`` ones in name order (a video or a survey line)."""
    if int(window) < 1:
        raise InputError(f"The sequential window must be at least 1 image, got {window!r}.")
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, min(len(names), i + 1 + window))]


def pairs_retrieval(features_path: str | Path, k: int, names: Sequence[str] | None = None) -> list[tuple[str, str]]:
    """Each image with its ``k`` most similar others by the global descriptor stored in features.h5."""
    if int(k) < 1:
        raise InputError(f"--retrieval needs at least 1 neighbour, got {k!r}.")
    names = list(names) if names is not None else list_feature_names(features_path)
    with open_h5(features_path, "Features file") as fd:
        missing = [n for n in names if n not in fd or "global_descriptor" not in fd[n]]
        if missing:
            raise InputError(f"Features file {features_path} has no global descriptor for {missing[0]!r}: retrieval "
                             f"needs an extractor with a global head (uwnet_xfeat, uwnet_mobilenet).")
        g = np.stack([fd[n]["global_descriptor"][()].astype(np.float32) for n in names])
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
    sim = g @ g.T
    np.fill_diagonal(sim, -np.inf)
    k = min(int(k), len(names) - 1)
    top = np.argsort(-sim, axis=1)[:, :k]
    return [(names[i], names[j]) for i in range(len(names)) for j in top[i]]


def unique_pairs(pairs: Sequence[tuple[str, str]]) -> list[tuple[str, str]]:
    """Pairs without repeats in either order, first occurrence kept."""
    seen, out = set(), []
    for a, b in pairs:
        if a == b or (a, b) in seen or (b, a) in seen:
            continue
        seen.add((a, b))
        out.append((a, b))
    return out


def make_pairs(names: Sequence[str], exhaustive: bool = False, window: int = 0, retrieval: int = 0,
               features_path: str | Path | None = None) -> list[tuple[str, str]]:
    """The union of the chosen strategies; ``exhaustive`` alone when set."""
    names = list(names)
    if len(names) < 2:
        raise InputError(f"Pairs need at least 2 images, got {len(names)}.")
    if exhaustive:
        return pairs_exhaustive(names)
    if not window and not retrieval:
        raise InputError("Choose a pairing: --exhaustive, --window K (sequential) and/or --retrieval K.")
    pairs = pairs_sequential(names, window) if window else []
    if retrieval:
        if features_path is None:
            raise InputError("--retrieval needs --features FEATURES.h5 holding global descriptors.")
        pairs += pairs_retrieval(features_path, retrieval, names)
    return unique_pairs(pairs)


# ---------------------------------------------------------------------------------------------------- matching


def mutual_nn(desc0: np.ndarray, desc1: np.ndarray, ratio: float | None = None, binary: bool = False,
              max_distance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours -> matches0 [N0] (-1 unmatched) and scores [N0] (cosine similarity, or
    1 - Hamming / bits for binary descriptors). ``ratio``: Lowe's test on distances."""
    n0 = len(desc0)
    m0, s0 = np.full(n0, -1, np.int64), np.zeros(n0, np.float32)
    if n0 == 0 or len(desc1) == 0:
        return m0, s0
    if binary:
        bits = np.unpackbits(desc0, axis=1).astype(np.float32), np.unpackbits(desc1, axis=1).astype(np.float32)
        d = (bits[0] @ (1 - bits[1]).T + (1 - bits[0]) @ bits[1].T) / bits[0].shape[1]
        sim = 1.0 - d
    else:
        sim = desc0.astype(np.float32) @ desc1.astype(np.float32).T
        d = np.sqrt(np.clip(2.0 - 2.0 * sim, 0.0, None))
    nn01 = np.argmin(d, axis=1)
    nn10 = np.argmin(d, axis=0)
    keep = nn10[nn01] == np.arange(n0)
    if ratio is not None and len(desc1) > 1:
        two = np.partition(d, 1, axis=1)[:, :2]
        keep &= two[:, 0] <= ratio * two[:, 1]
    if max_distance is not None:
        keep &= d[np.arange(n0), nn01] <= max_distance
    m0[keep] = nn01[keep]
    s0[keep] = sim[np.arange(n0), nn01][keep]
    return m0, s0


LIGHTGLUE_FEATURES = {64: "xfeat", 128: "aliked"}  # descriptor width -> LightGlue weights (ALIKED and DISK: 128)


def match_features(features_path: str | Path, pairs: Sequence[tuple[str, str]], out_path: str | Path,
                   matcher: str = "nn", ratio: float | None = None, lightglue_features: str | None = None,
                   progress: bool = True) -> dict:
    """Match every pair and write hloc's matches.h5. Returns {"pairs", "matches", "seconds"}."""
    if matcher not in ("nn", "lightglue"):
        raise InputError(f"Unknown matcher {matcher!r}; expected 'nn' or 'lightglue'.")
    if ratio is not None and not 0 < float(ratio) <= 1:
        raise InputError(f"The ratio test threshold must be in (0, 1], got {ratio!r}.")
    pairs = list(pairs)
    if not pairs:
        raise InputError("No pairs to match.")
    known = set(list_feature_names(features_path))
    for a, b in pairs:
        for n in (a, b):
            if n not in known:
                raise InputError(f"Pair ({a}, {b}) names {n!r}, which features file {features_path} does not hold.")
    cache: dict[str, dict] = {}

    def get(name):
        if name not in cache:
            cache[name] = read_features(features_path, name)
        return cache[name]

    lg = None
    if matcher == "lightglue":
        dim = get(pairs[0][0])["descriptors"].shape[1]
        features = lightglue_features or LIGHTGLUE_FEATURES.get(dim)
        if features is None:
            raise InputError(f"No LightGlue weights for {dim}-d descriptors; use --matcher nn.")
        from ruslam.models.lightglue import LightGlueMatcher  # noqa: PLC0415 (torch only when needed)

        lg = LightGlueMatcher(features)
    total, start = 0, time.perf_counter()
    with atomic_path(out_path) as tmp, h5py.File(tmp, "w", libver="latest") as fd:
        for a, b in tqdm(pairs, desc="matching", unit="pair", disable=not progress):
            f0, f1 = get(a), get(b)
            if lg is None:
                m0, s0 = mutual_nn(f0["descriptors"], f1["descriptors"], ratio,
                                   binary=f0["descriptors"].dtype == np.uint8)
            else:
                i0, i1 = lg(f0["keypoints"], f0["descriptors"].astype(np.float32), f0["image_size"],
                            f1["keypoints"], f1["descriptors"].astype(np.float32), f1["image_size"])
                m0 = np.full(len(f0["keypoints"]), -1, np.int64)
                m0[i0] = i1
                s0 = (m0 >= 0).astype(np.float32)
            write_matches_group(fd, a, b, m0, s0, len(f1["keypoints"]))
            total += int((m0 >= 0).sum())
    return {"pairs": len(pairs), "matches": total, "seconds": time.perf_counter() - start}
