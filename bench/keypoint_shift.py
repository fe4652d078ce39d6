"""Do keypoints move with the image? Re-detection after an integer shift, for each extractor.

    nice .venv/bin/python bench/keypoint_shift.py IMAGE [--extractors xfeat orb] [--conditioning clahe]

The image (after the SLAM's conditioning) is shifted down by 1-16 px (reflected border, no resampling), and each
keypoint of the original is looked for within 2.5 px of where the shift puts it. A detector that is equivariant to
translation finds (nearly) all of them exactly, whatever the shift; a strided network is exactly equivariant only
to multiples of its stride, and a shift-dependent mean error is a bias the SLAM sees as motion (flow between
frames is a shift, locally).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ruslam import load_extractor  # noqa: E402
from ruslam.slam.conditioning import ImageConditioning  # noqa: E402

PAD = 16


def shifted(image: np.ndarray, dy: int) -> np.ndarray:
    """`image` with its content moved down by dy px (0 <= dy <= PAD), same size."""
    big = cv2.copyMakeBorder(image, PAD, PAD, 0, 0, cv2.BORDER_REFLECT)
    return np.ascontiguousarray(big[PAD - dy: PAD - dy + image.shape[0]])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("image")
    ap.add_argument("--extractors", nargs="+", default=["xfeat", "orb"])
    ap.add_argument("--max-keypoints", type=int, default=1000)
    ap.add_argument("--conditioning", default="clahe", help="none | clahe | auto (1 px blur first unless none)")
    args = ap.parse_args()
    image = cv2.imread(args.image, cv2.IMREAD_COLOR)
    if image is None:
        raise SystemExit(f"{args.image}: not an image OpenCV can read.")
    sigma = 0.0 if args.conditioning == "none" else 1.0
    image = ImageConditioning(method=args.conditioning, blur_sigma=sigma)(image[:, :, ::-1].copy())
    print(f"{Path(args.image).name} {image.shape[1]}x{image.shape[0]}, conditioning {args.conditioning}")
    print("| extractor | shift (px) | re-detected within 2.5 px | exactly (< 0.01 px) | mean error along it (px) |")
    print("|---|---:|---:|---:|---:|")
    for name in args.extractors:
        extractor = load_extractor(name, max_keypoints=args.max_keypoints)
        k0 = extractor.extract(image)["keypoints"]
        for dy in range(1, PAD + 1):
            k = extractor.extract(shifted(image, dy))["keypoints"]
            dist, j = cKDTree(k).query(k0 + [0, dy])
            found = dist < 2.5
            err = k[j[found]] - (k0[found] + [0, dy])
            exact = np.mean(np.abs(err).sum(1) < 0.01) if found.any() else 0.0
            print(f"| {name} | {dy} | {found.mean():.2f} | {exact * found.mean():.2f} | {err[:, 1].mean():+.3f} |")


if __name__ == "__main__":
    main()
