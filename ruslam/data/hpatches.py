"""Reader of the official HPatches layout; Upatches (`ruslam.data.upatches`) is written in the same layout.

A root holds sequence folders (``i_*`` illumination, ``v_*`` viewpoint), each with ``1.ppm`` ... ``N.ppm`` and
``H_1_2`` ... ``H_1_N`` (3x3 text matrices mapping pixels of image 1 to pixels of image k). An optional
``rotation_deg.txt`` (one value per pair, written by the Upatches builder) gives the in-plane rotation of each
pair; without it the rotation is measured from H at the centre of image 1.

Every image is resized to one evaluation size (480x640 by default, aspect ratio not kept, as in SuperPoint and
HF-Net) and H follows exactly: H' = S2 H S1^-1, where S maps pixel centres of the original to the resized image.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np


def read_image(path: Path) -> np.ndarray:
    """uint8 HxWx3 RGB, or one clear error when the file is not a readable image."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Image file {path} does not exist.")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"Cannot read image {path}: it is not a readable image file (corrupt or unknown format).")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_homography(path: Path) -> np.ndarray:
    """A 3x3 float64 matrix from a whitespace-separated text file, or one clear error."""
    path = Path(path)
    try:
        H = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise ValueError(f"Cannot read homography file {path}: expected 3 rows of 3 numbers ({exc}).") from None
    if H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
        raise ValueError(f"Homography file {path} must hold an invertible 3x3 matrix, got shape {H.shape}.")
    return H


def resize_matrix(from_hw: tuple[int, int], to_hw: tuple[int, int]) -> np.ndarray:
    """3x3 map of pixel coordinates under a resize: x' = (x + 0.5) * sx - 0.5 (pixel centres, as cv2.resize)."""
    sy, sx = to_hw[0] / from_hw[0], to_hw[1] / from_hw[1]
    return np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]], dtype=np.float64)


def resize_homography(H: np.ndarray, hw1: tuple, hw2: tuple, to_hw: tuple) -> np.ndarray:
    """H between original images of sizes hw1, hw2 -> H between both resized to to_hw: S2 H S1^-1."""
    return resize_matrix(hw2, to_hw) @ H @ np.linalg.inv(resize_matrix(hw1, to_hw))


def resize_image(image: np.ndarray, to_hw: tuple[int, int] | None) -> np.ndarray:
    if to_hw is None or tuple(image.shape[:2]) == tuple(to_hw):
        return image
    shrink = to_hw[0] * to_hw[1] < image.shape[0] * image.shape[1]
    return cv2.resize(image, (to_hw[1], to_hw[0]), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def rotation_from_homography(H: np.ndarray, hw1: tuple[int, int]) -> float:
    """In-plane rotation (degrees, (-180, 180]) of a unit step along x at the centre of image 1 under H."""
    c = np.array([(hw1[1] - 1) / 2, (hw1[0] - 1) / 2, 1.0])
    p, q = H @ c, H @ (c + np.array([1.0, 0, 0]))
    d = q[:2] / q[2] - p[:2] / p[2]
    return float(np.degrees(np.arctan2(d[1], d[0])))


def zoom_from_homography(H: np.ndarray, hw2: tuple[int, int]) -> float:
    """Linear magnification of image 2 over image 1 at the centre of image 2: sqrt |det J| of H there."""
    Hinv = np.linalg.inv(H)
    c = Hinv @ np.array([(hw2[1] - 1) / 2, (hw2[0] - 1) / 2, 1.0])
    x = c / c[2]
    p = H @ x
    # Jacobian of (u, v) = (p0 / p2, p1 / p2) with respect to (x, y)
    J = (H[:2, :2] * p[2] - np.outer(p[:2], H[2, :2])) / p[2] ** 2
    return float(np.sqrt(abs(np.linalg.det(J))))


@dataclass
class Sequence:
    name: str
    images: list[Path]  # 1.ppm ... N.ppm
    homographies: list[np.ndarray]  # H_1_2 ... H_1_N at original resolution
    rotations_deg: list[float] | None  # from rotation_deg.txt, else None (measured from H on use)


def read_sequence(folder: Path) -> Sequence:
    folder = Path(folder)
    images = []
    k = 1
    while (folder / f"{k}.ppm").is_file():
        images.append(folder / f"{k}.ppm")
        k += 1
    if len(images) < 2:
        raise ValueError(f"Sequence folder {folder} must hold at least 1.ppm and 2.ppm, found {len(images)} image(s).")
    homographies = []
    for k in range(2, len(images) + 1):
        path = folder / f"H_1_{k}"
        if not path.is_file():
            raise FileNotFoundError(f"Sequence folder {folder} has {k}.ppm but no homography file H_1_{k}.")
        homographies.append(read_homography(path))
    rotations = None
    if (folder / "rotation_deg.txt").is_file():
        rotations = np.loadtxt(folder / "rotation_deg.txt", dtype=np.float64, ndmin=1).tolist()
        if len(rotations) != len(homographies):
            raise ValueError(
                f"{folder / 'rotation_deg.txt'} must hold {len(homographies)} values (one per pair), "
                f"got {len(rotations)}."
            )
    return Sequence(folder.name, images, homographies, rotations)


class HPatches:
    """Map-style dataset of homography pairs (1, k) of every sequence; `__getitem__` loads the images.

    ``kinds``: sequence-name prefixes to keep (``["i", "v"]`` for both HPatches halves; None keeps all).
    ``size``: (height, width) every image is resized to, or None for the native sizes.
    """

    def __init__(self, root: str | Path, size=(480, 640), kinds=None, max_sequences: int | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"HPatches root {self.root} is not a folder.")
        self.size = None if size is None else (int(size[0]), int(size[1]))
        folders = sorted(p for p in self.root.iterdir() if p.is_dir() and (p / "1.ppm").is_file())
        if kinds is not None:
            folders = [p for p in folders if p.name.split("_")[0] in set(kinds)]
        if max_sequences is not None:
            folders = folders[: int(max_sequences)]
        if not folders:
            raise ValueError(
                f"HPatches root {self.root} holds no sequence folder (with 1.ppm) of kinds {kinds}; "
                "expected folders like i_*/ or v_*/ with 1.ppm ... 6.ppm and H_1_2 ... H_1_6."
            )
        self.sequences = [read_sequence(p) for p in folders]
        self.pairs = [(s, k) for s in range(len(self.sequences)) for k in range(len(self.sequences[s].homographies))]

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> dict:
        """{"sequence", "name", "image1", "image2" (uint8 RGB at `size`), "H" (image 1 -> 2 at `size`),
        "rotation_deg", "zoom" (magnification of image 2 over image 1 at its centre, `zoom_from_homography`)}."""
        s, k = self.pairs[i]
        seq = self.sequences[s]
        image1, image2 = read_image(seq.images[0]), read_image(seq.images[k + 1])
        H = seq.homographies[k]
        hw1, hw2 = image1.shape[:2], image2.shape[:2]
        rotation = seq.rotations_deg[k] if seq.rotations_deg is not None else rotation_from_homography(H, hw1)
        if self.size is not None:
            H = resize_homography(H, hw1, hw2, self.size)
        return {
            "sequence": seq.name,
            "name": f"{seq.name}/1-{k + 2}",
            "image1": resize_image(image1, self.size),
            "image2": resize_image(image2, self.size),
            "H": H,
            "rotation_deg": float(rotation),
            "zoom": zoom_from_homography(H, self.size or hw2),
        }
