"""Procedural RGB-D rendering speed against reading the same images from disk as a real RGB-D dataset would.

Baseline (same run): the rendered samples are written as 8-bit PNG colour + 16-bit PNG depth (mm) and read back
with `RGBDFolder`, i.e. the cost of a real RGB-D source's decoding.  Ratio < 1 means rendering is cheaper than that.
Times are per image, both wall clock and process CPU time (the CPU time is robust to other jobs on shared cores).

    nice .venv/bin/python bench/procedural.py [--images 16]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ruslam.data.procedural import ProceduralRGBD
from ruslam.data.procedural_textures import texture_bank
from ruslam.data.rgbd_folder import RGBDFolder


def per_image(fn, n: int) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    for i in range(n):
        fn(i)
    return (time.perf_counter() - wall) / n, (time.process_time() - cpu) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=16)
    n = parser.parse_args().images

    wall, cpu = time.perf_counter(), time.process_time()
    texture_bank(0)
    print(f"texture bank (48 textures + mips, once per process): wall {time.perf_counter() - wall:.2f} s, "
          f"cpu {time.process_time() - cpu:.2f} s")
    print("| size | procedural wall | procedural cpu | disk read wall (baseline) | disk read cpu | cpu ratio |")
    print("|---|---|---|---|---|---|")
    for h, w in ((240, 320), (480, 640)):
        ds = ProceduralRGBD(n, h, w, seed=0)
        ds[0]  # warm-up
        render_wall, render_cpu = per_image(ds.__getitem__, n)
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp)
            (root / "color").mkdir(), (root / "depth").mkdir()
            for i in range(n):
                s = ds[i]
                cv2.imwrite(str(root / "color" / f"{i}.png"), (s["image"][..., ::-1] * 255 + 0.5).astype(np.uint8))
                cv2.imwrite(str(root / "depth" / f"{i}.png"), np.round(s["depth"] * 1000).astype(np.uint16))
            folder = RGBDFolder(root, depth_scale=1000.0)
            folder[0]
            read_wall, read_cpu = per_image(folder.__getitem__, n)
        print(f"| {h}x{w} | {render_wall * 1e3:.0f} ms | {render_cpu * 1e3:.0f} ms | {read_wall * 1e3:.0f} ms | "
              f"{read_cpu * 1e3:.0f} ms | x{render_cpu / read_cpu:.2f} |")


if __name__ == "__main__":
    main()
