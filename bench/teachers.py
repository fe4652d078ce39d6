"""Teacher throughput at 480x640 and teacher-cache read vs recomputing the teachers, in one run.

    nice .venv/bin/python bench/teachers.py [--images 8] [--threads 2]

Prints images/s of the XFeat teacher (dense), the SuperPoint architecture (random weights; same FLOPs as the real
one), the offline XFeat+VLAD teacher (what the cache stores) and sparse `load_extractor("xfeat")`; then builds a
cache of the same images and reports reading one image's targets vs recomputing them (ratio, target >= 10x).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import cv2
import numpy as np
import torch

from ruslam import load_extractor
from ruslam.data.teacher_cache import build_cache
from ruslam.models.pretrained import Teacher
from ruslam.models.pretrained.superpoint import SuperPointNet, SuperPointTeacher
from ruslam.models.pretrained.vlad import VLAD
from ruslam.models.pretrained.xfeat import XFeatTeacher

H, W = 480, 640


class Images:
    """Seeded textured images (smooth blobs + rectangles), the dataset contract {"id", "image"}."""

    def __init__(self, n: int):
        self.n = n

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        rng = np.random.default_rng(i)
        img = cv2.resize(rng.random((H // 16, W // 16, 3)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
        for _ in range(60):
            x, y = rng.integers(0, W - 40), rng.integers(0, H - 40)
            img[y : y + rng.integers(10, 80), x : x + rng.integers(10, 80)] = rng.random(3)
        return {"id": f"bench/{i:04d}", "image": np.clip(img, 0, 1)}


def seconds_per_call(fn, inputs, repeats: int = 1) -> float:
    fn(inputs[0])  # warm-up
    times = []
    for _ in range(repeats):
        for x in inputs:
            t0 = time.perf_counter()
            fn(x)
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dataset = Images(args.images)
    arrays = [dataset[i]["image"] for i in range(len(dataset))]
    tensors = [torch.from_numpy(a).permute(2, 0, 1)[None].contiguous() for a in arrays]

    with tempfile.TemporaryDirectory() as tmp:
        teacher = Teacher(XFeatTeacher(), VLAD(fit_images=args.images, fit_descriptors_per_image=400))
        teacher.prepare(dataset, tmp)  # fit the codebook on these images, as the cache build does
        superpoint = SuperPointTeacher(net=SuperPointNet())
        xfeat_sparse = load_extractor("xfeat")
        with torch.inference_mode():
            rows = {
                "XFeat teacher (dense, 1/8)": seconds_per_call(teacher.local, tensors),
                "SuperPoint architecture (dense, random weights)": seconds_per_call(superpoint, tensors[:3]),
                "XFeat + VLAD teacher (cached targets)": seconds_per_call(teacher, tensors),
                'load_extractor("xfeat").extract (2k sparse + global)': seconds_per_call(xfeat_sparse.extract, arrays),
            }
        recompute = rows["XFeat + VLAD teacher (cached targets)"]

        cache = build_cache(dataset, teacher, tmp, float16=True)
        ids = [dataset[i]["id"] for i in range(len(dataset))]
        read = seconds_per_call(cache.read, ids, repeats=5)

    print(f"# teachers at {H}x{W}, {args.threads} threads, {args.images} images (median per image)")
    print("| what | ms/image | images/s |")
    print("|---|---|---|")
    for name, sec in rows.items():
        print(f"| {name} | {sec * 1e3:.1f} | {1 / sec:.1f} |")
    print(f"| teacher cache read (float16, lzf) | {read * 1e3:.2f} | {1 / read:.0f} |")
    print(f"\ncache read vs recomputing the XFeat+VLAD teacher: {recompute / read:.0f}x faster")


if __name__ == "__main__":
    main()
