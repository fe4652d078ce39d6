"""Benchmark of the synthetic seafloor sequence: ray-cast cost and accuracy, and a default sequence's generation.

    nice .venv/bin/python bench/synthetic_sequence.py [--frames 200] [--views 8]

Baseline (same process): a brute-force march of 96 fixed steps with linear interpolation of the last step, the
straightforward way to ray-cast a height field. Ours: 12 march steps + 3 regula-falsi refinements. Accuracy is
the largest distance between a hit point and the height field at its x, y (0 for an exact intersection).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ruslam.data.synthetic_sequence import (
    SeafloorConfig,
    circuit_poses,
    make_seafloor,
    pixel_rays,
    render,
    synthetic_sequence,
)


def brute_force(floor, rays, pose, steps=96):
    d = rays @ pose[:3, :3].T.astype(np.float32)
    o = pose[:3, 3].astype(np.float32)
    t_top = (o[2] - floor.height.max()) / -d[..., 2]
    span = (o[2] - floor.height.min()) / -d[..., 2] - t_top
    prev_t, prev_g = t_top, None
    hit = np.full(t_top.shape, np.nan, np.float32)
    for k in range(steps + 1):
        t = t_top + span * (k / steps)
        X = o + t[..., None] * d
        g = X[..., 2] - floor.height_at(X[..., 0], X[..., 1])
        if prev_g is not None:
            new = np.isnan(hit) & (g <= 0)
            hit[new] = (prev_t + (t - prev_t) * prev_g / np.maximum(prev_g - g, 1e-9))[new]
        prev_t, prev_g = t, g
    tg = floor.texture.shape[0] / (2 * floor.half)
    X = o + hit[..., None] * d
    cv2.remap(floor.texture, (X[..., 0] + floor.half) * tg - 0.5, (X[..., 1] + floor.half) * tg - 0.5,
              cv2.INTER_LINEAR)
    return hit


def surface_error(floor, rays, pose, t):
    X = pose[:3, 3] + t[..., None] * (rays @ pose[:3, :3].T)
    return np.abs(X[..., 2] - floor.height_at(X[..., 0], X[..., 1]))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--views", type=int, default=8)
    args = parser.parse_args()
    cfg = SeafloorConfig(num_frames=args.frames)
    start = time.perf_counter()
    floor = make_seafloor(cfg)
    print(f"seafloor build: {time.perf_counter() - start:.1f} s")
    rays, poses = pixel_rays(cfg.camera()), circuit_poses(cfg)[:: max(1, args.frames // args.views)][: args.views]
    timings = {}
    errors = {}
    for name, fn in [("brute force 96 steps", lambda p: brute_force(floor, rays, p)),
                     ("ours 12 steps + 3 regula falsi", lambda p: render(floor, rays, p)[1])]:
        start = time.perf_counter()
        ts = [fn(p) for p in poses]
        timings[name] = (time.perf_counter() - start) / len(poses)
        errors[name] = max(float(np.nanmax(surface_error(floor, rays, p, t))) for p, t in zip(poses, ts, strict=True))
    base = timings["brute force 96 steps"]
    for name in timings:
        print(f"{name:32s} {1000 * timings[name]:7.1f} ms/view  x{base / timings[name]:.2f} vs brute force  "
              f"max surface error {1000 * errors[name]:.2f} mm")
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        synthetic_sequence("clear", cache_dir=Path(tmp), num_frames=args.frames, progress=False)
        total = time.perf_counter() - start
    render_only = timings["ours 12 steps + 3 regula falsi"] * args.frames
    print(f"default mono sequence ({args.frames} frames, 640x480, clean level, PNG + range): {total:.1f} s "
          f"= x{total / render_only:.2f} of its ray-casting time alone ({render_only:.1f} s)")


if __name__ == "__main__":
    main()
