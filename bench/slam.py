"""SLAM throughput at 640x480 on 2 threads, synchronous mode (mapping and loop closing inline), XFeat and ORB.

    nice .venv/bin/python bench/slam.py [--frames 100] [--level clear] [--extractors xfeat orb] [--stereo] [--no-loop]

For each extractor the baseline is feature extraction alone on the same frames, measured in this same run; the
SLAM figure is frames / (sum of per-frame times: extraction + tracking + inline mapping + loop closing), so the
ratio says what the SLAM adds on top of the extractor. Accuracy (APE after Sim3/SE3 alignment, % of path) is
printed alongside, so a faster setting that breaks tracking shows up. Goals (issue 6): >= 10 frames/s with the
learned extractor, >= 25 with ORB.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import torch

from ruslam import load_extractor
from ruslam.eval.trajectory import evaluate_trajectory
from ruslam.slam import SLAMConfig, run
from ruslam.slam.loop_closing import LoopConfig
from ruslam.slam.readers import Trajectory
from ruslam.slam.synthetic_sequence import synthetic_sequence


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100, help="first frames of the 200-frame sequence")
    parser.add_argument("--level", default="clear")
    parser.add_argument("--extractors", nargs="+", default=["xfeat", "orb"])
    parser.add_argument("--stereo", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-loop", action="store_true", help="disable loop closing (APE with vs without)")
    parser.add_argument("--global-ba", action="store_true", help="full-map BA after a loop correction")
    parser.add_argument("--max-keypoints", type=int, default=None, help="extractor keypoint cap (default: its own)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)
    seq = synthetic_sequence(args.level, stereo=args.stereo, num_frames=200, seed=0, progress=False)
    n = min(args.frames, len(seq))
    images = [seq.load(i) for i in range(n)]
    gt = Trajectory(seq.groundtruth.timestamps[:n], seq.groundtruth.poses[:n])
    print(f"sequence {seq.name}: {n} frames {seq.cameras[0].width}x{seq.cameras[0].height}, "
          f"{'stereo' if args.stereo else 'mono'}, path {gt.path_length():.2f} m, torch threads {args.threads}")
    print(f"{'extractor':10s} {'extract fps':>11s} {'SLAM fps':>9s} {'ratio':>6s} {'tracked':>8s} {'kfs':>4s} "
          f"{'loops':>5s} {'APE m':>7s} {'APE %path':>9s}")
    for name in args.extractors:
        extractor = load_extractor(name, **({} if args.max_keypoints is None else
                                            {"max_keypoints": args.max_keypoints}))
        extractor.extract(images[0][0])  # warm-up
        start = time.perf_counter()
        for frame in images:
            for image in frame:
                extractor.extract(image)
        extract_fps = n / (time.perf_counter() - start)
        cfg = SLAMConfig(progress=False, synchronous=True, max_frames=n, loop=LoopConfig(enabled=not args.no_loop,
                                                                                   global_bundle_adjustment=args.global_ba))
        result = run(seq, extractor, cfg)
        slam_fps = n / float(result.timings.sum())
        ape = float("nan")
        if len(result) >= 3:
            errors = evaluate_trajectory(Trajectory(result.timestamps, result.poses), gt,
                                         "se3" if args.stereo else "sim3")
            ape = errors.ape_rmse
        print(f"{name:10s} {extract_fps:11.1f} {slam_fps:9.1f} {slam_fps / extract_fps:6.2f} "
              f"{result.tracked_ratio:8.1%} {result.num_keyframes:4d} {len(result.loops):5d} {ape:7.4f} "
              f"{100 * ape / gt.path_length():9.2f}")
        per_frame = np.sort(result.timings)
        print(f"{'':10s} per-frame ms: median {1e3 * np.median(per_frame):.0f}, p90 "
              f"{1e3 * per_frame[int(0.9 * (n - 1))]:.0f}, max {1e3 * per_frame[-1]:.0f}")


if __name__ == "__main__":
    main()
