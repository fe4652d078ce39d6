"""Pseudo-underwater synthesis throughput at 480x640: batched torch eq. 4 vs numpy references of the same formula.

    nice .venv/bin/python bench/synthesis.py [--batch 8] [--reps 5] [--threads 2]

Measured in one run on the same inputs: `PseudoUnderwater` (random Jerlov type, A, L, noise; 20 deg / 10 px PSF)
on batches of ``--batch`` images; a plain per-pixel numpy reference (a Python loop over pixels, each pixel doing
eq. 4 with its PSF taps); and, as a stronger baseline, a vectorized numpy version (whole-array operations).
The torch CPU time per image is printed too: on a shared machine the wall-clock rate depends on the load.
Before timing, both references are checked to give the torch result (noise off). Targets: >= 30 images/s on 2
cores and >= 20x the per-pixel numpy reference.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from ruslam.data.synthesis import PseudoUnderwater, degrade, motion_kernel

H, W = 480, 640


def inputs(batch: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rgb = rng.random((batch, 3, H, W), dtype=np.float32)
    depth = (0.5 + 8 * rng.random((batch, H, W))).astype(np.float32)
    depth[:, :20] = np.nan  # some invalid depth, as in Kinect maps
    return rgb, depth


def taps(angle: float, length: float) -> list[tuple[int, int, float]]:
    k = motion_kernel(angle, length).numpy()
    r = k.shape[0] // 2
    return [(i - r, j - r, float(k[i, j])) for i, j in zip(*np.nonzero(k), strict=True)]


def _reflect(i: int, n: int) -> int:
    return -i if i < 0 else (2 * (n - 1) - i if i >= n else i)


def per_pixel_numpy(rgb, depth, beta, A, L, noise_std, kernel_taps, rng) -> np.ndarray:
    """Eq. 4 for one image [3,H,W], one pixel at a time (the plain reference)."""
    _, h, w = rgb.shape
    illum = L * A
    valid = np.isfinite(depth) & (depth > 0)
    t = np.where(valid, np.exp(-beta[:, None, None] * np.where(valid, depth, 0.0)), 0.0)
    direct = illum[:, None, None] * rgb * t
    out = np.empty_like(rgb)
    noise = rng.standard_normal(rgb.shape) * noise_std
    for c in range(3):
        for y in range(h):
            for x in range(w):
                blurred = 0.0
                for dy, dx, wt in kernel_taps:
                    blurred += wt * direct[c, _reflect(y + dy, h), _reflect(x + dx, w)]
                value = blurred + illum[c] * (1.0 - t[c, y, x]) + noise[c, y, x]
                out[c, y, x] = min(max(value, 0.0), 1.0)
    return out


def vectorized_numpy(rgb, depth, beta, A, L, noise_std, kernel_taps, rng) -> np.ndarray:
    """Eq. 4 for one image [3,H,W] with whole-array numpy operations."""
    illum = (L * A)[:, None, None]
    valid = np.isfinite(depth) & (depth > 0)
    t = np.where(valid, np.exp(-beta[:, None, None] * np.where(valid, depth, 0.0)), 0.0)
    direct = illum * rgb * t
    r = max(max(abs(dy), abs(dx)) for dy, dx, _ in kernel_taps)
    padded = np.pad(direct, ((0, 0), (r, r), (r, r)), mode="reflect")
    _, h, w = rgb.shape
    blurred = sum(wt * padded[:, r + dy:r + dy + h, r + dx:r + dx + w] for dy, dx, wt in kernel_taps)
    out = blurred + illum * (1 - t) + noise_std * rng.standard_normal(rgb.shape)
    return np.clip(out, 0.0, 1.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rgb, depth = inputs(args.batch)
    synth = PseudoUnderwater(seed=0)
    kernel_taps = taps(synth.blur_angle_deg, synth.blur_length)

    # Same formula: torch degrade vs both numpy references, noise off.
    p = synth.params(0)
    args0 = (rgb[0].astype(np.float64), depth[0].astype(np.float64), p["beta"], p["A"], p["L"], 0.0, kernel_taps,
             np.random.default_rng(0))
    ref = vectorized_numpy(*args0)
    crop = (rgb[0][:, :40, :60].astype(np.float64), depth[0][:40, :60].astype(np.float64), *args0[2:])
    ref_pix = per_pixel_numpy(*crop)
    ten = lambda *a: torch.as_tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
    got = degrade(torch.from_numpy(rgb[:1]), torch.from_numpy(depth[:1]), ten(p["beta"]), ten(p["A"]), ten(p["L"]),
                  ten(0.0), synth.blur_angle_deg, synth.blur_length)[0].numpy()
    got_crop = degrade(torch.from_numpy(rgb[:1, :, :40, :60]), torch.from_numpy(depth[:1, :40, :60]), ten(p["beta"]),
                       ten(p["A"]), ten(p["L"]), ten(0.0), synth.blur_angle_deg, synth.blur_length)[0].numpy()
    err, err_pix = float(np.abs(got - ref).max()), float(np.abs(got_crop - ref_pix).max())
    assert err < 1e-5 and err_pix < 1e-5, (err, err_pix)

    rgb_t, depth_t = torch.from_numpy(rgb), torch.from_numpy(depth)
    synth(rgb_t, depth_t, list(range(args.batch)))  # warm-up
    torch_s, torch_cpu, vec_s = [], [], []
    for rep in range(args.reps):  # interleaved so that machine load hits both alike
        t0, c0 = time.perf_counter(), time.process_time()
        synth(rgb_t, depth_t, [rep * args.batch + i for i in range(args.batch)])
        torch_s.append((time.perf_counter() - t0) / args.batch)
        torch_cpu.append((time.process_time() - c0) / args.batch)
        rng = np.random.default_rng(rep)
        t0 = time.perf_counter()
        vectorized_numpy(rgb[rep % args.batch], depth[rep % args.batch], p["beta"], p["A"], p["L"], 0.01,
                         kernel_taps, rng)
        vec_s.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    per_pixel_numpy(rgb[0], depth[0], p["beta"], p["A"], p["L"], 0.01, kernel_taps, np.random.default_rng(0))
    pix_s = time.perf_counter() - t0

    t, v = statistics.median(torch_s), statistics.median(vec_s)
    print(f"480x640, {args.threads} threads, batch {args.batch}, {args.reps} reps (median), "
          f"load average {os.getloadavg()[0]:.1f}; max |torch - numpy| = {err:.1e} (full), {err_pix:.1e} (crop)")
    print("| implementation | ms / image | images / s | torch speed-up |")
    print("|---|---|---|---|")
    print(f"| torch batched (`PseudoUnderwater`) | {t * 1e3:.1f} | {1 / t:.1f} | 1.0x |")
    print(f"| numpy vectorized | {v * 1e3:.1f} | {1 / v:.1f} | {v / t:.1f}x |")
    print(f"| numpy per-pixel (reference) | {pix_s * 1e3:.0f} | {1 / pix_s:.3f} | {pix_s / t:.0f}x |")
    c = statistics.median(torch_cpu)
    print(f"torch CPU time (all threads) {c * 1e3:.1f} ms / image: {args.threads / c:.0f} images/s if the "
          f"{args.threads} cores were free (the wall-clock rows above share the machine with its load)")


if __name__ == "__main__":
    main()
