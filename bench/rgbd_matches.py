"""How many matches between consecutive frames of an RGB-D sequence are correct, by the ground truth: an upper
bound on what a monocular tracker can use, whatever its logic.

    nice .venv/bin/python bench/rgbd_matches.py ROOT [--extractors xfeat orb sift aliked] [--max-keypoints 2000]
    nice .venv/bin/python bench/rgbd_matches.py ROOT --extractors xfeat --max-keypoints 4096 --xfeat-threshold 0.01
    nice .venv/bin/python bench/rgbd_matches.py ROOT --extractors xfeat --xfeat-resize-min 1280   # XFeat on 2x frames
    nice .venv/bin/python bench/rgbd_matches.py ROOT --extractors xfeat aliked --lightglue   # by (Lighter)LightGlue
    nice .venv/bin/python bench/rgbd_matches.py ROOT --extractors xfeat --lightglue --pairs 55:0 57:0 57:1  # loop pairs

ROOT is a TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt; e.g. keyframes of TUM fr3 cabinet). For each
pair (i, i+step), the SLAM's matcher (mutual nearest neighbours, ratio 0.8, the tracker's distance gate) matches
the two keypoint sets; a match is correct when the keypoint of frame i, lifted with its depth and moved by the true
relative pose, lands within 4 px of its partner in frame i+step. A tracked frame needs ~30
(`tracking.min_inliers`). `--lightglue` matches with LightGlue instead (`ruslam.models.lightglue`: LighterGlue for
XFeat, LightGlue's ALIKED weights for ALIKED): what a learned matcher would give the tracker. `--pairs I:J` counts
named pairs instead, one line each (e.g. the revisit at the end of a loop, for loop verification).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from ruslam import load_extractor
from ruslam.data.readers import read_tum_trajectory
from ruslam.data.sequence_folder import read_sequence
from ruslam.models.feature_matching import match_knn_ratio
from ruslam.models.lightglue import WEIGHTS, LightGlueMatcher
from ruslam.slam.tracking import TrackingConfig

DEPTH_SCALE = 5000.0  # TUM: 16-bit depth PNG, metres = value / 5000


def correct_matches(k1, k2, depth1, K, T_21, max_px=4.0) -> np.ndarray:
    """[M] bool: k1 lifted with depth1 and moved by T_21 projects within max_px of k2 (no depth: not correct)."""
    u = np.clip(np.round(k1).astype(int), 0, [depth1.shape[1] - 1, depth1.shape[0] - 1])
    z = depth1[u[:, 1], u[:, 0]]
    X = np.c_[(k1 - K[:2, 2]) / K[[0, 1], [0, 1]] * z[:, None], z]
    Y = X @ T_21[:3, :3].T + T_21[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = Y[:, :2] / Y[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]
        return (z > 0) & (Y[:, 2] > 0) & (np.linalg.norm(uv - k2, axis=1) < max_px)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", help="a TUM RGB-D folder")
    ap.add_argument("--extractors", nargs="+", default=["xfeat", "orb", "sift", "aliked"])
    ap.add_argument("--max-keypoints", type=int, default=2000)
    ap.add_argument("--xfeat-threshold", type=float, default=None, help="XFeat's detection threshold (its own: 0.05)")
    ap.add_argument("--xfeat-resize-min", type=int, default=None, help="XFeat's resize_min (upsample smaller frames)")
    ap.add_argument("--lightglue", action="store_true", help="match with LightGlue instead of kNN (xfeat, aliked)")
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--pairs", nargs="+", default=None, metavar="I:J", help="frame pairs instead of --steps")
    args = ap.parse_args()
    try:
        pairs = [tuple(int(v) for v in p.split(":")) for p in args.pairs or []]
    except ValueError:
        raise SystemExit(f"--pairs takes I:J frame indices, got {args.pairs}.") from None
    root = Path(args.root)
    seq = read_sequence(root)
    depth_files = [line.split()[1] for line in (root / "depth.txt").read_text().splitlines()
                   if line.strip() and not line.startswith("#")]
    if len(depth_files) != len(seq):
        raise SystemExit(f"{root}/depth.txt lists {len(depth_files)} images, rgb.txt {len(seq)}: expected one each.")
    gt = read_tum_trajectory(root / "groundtruth.txt")
    T_wc = [gt.poses[int(np.argmin(np.abs(gt.timestamps - t)))] for t in seq.timestamps]
    K = seq.cameras[0].K
    depths = [cv2.imread(str(root / f), cv2.IMREAD_UNCHANGED).astype(np.float64) / DEPTH_SCALE for f in depth_files]
    gate = TrackingConfig()
    print(f"{root.name}: {len(seq)} frames; correct = within 4 px by depth + true pose")
    if any(len(p) != 2 or not all(0 <= v < len(seq) for v in p) for p in pairs):
        raise SystemExit(f"--pairs {args.pairs}: expected I:J with frame indices in 0..{len(seq) - 1}.")
    if not pairs:
        print("extractor  step  keypoints  matches  correct: median  p10  pairs >= 30  pairs >= 50  inlier share")
    for name in args.extractors:
        try:
            options = {} if name == "sift" else {"max_keypoints": args.max_keypoints}
            if name == "xfeat" and args.xfeat_threshold is not None:
                options["detection_threshold"] = args.xfeat_threshold
            if name == "xfeat" and args.xfeat_resize_min is not None:
                options["resize_min"] = args.xfeat_resize_min
            ex = load_extractor(name, **options)
        except (ImportError, FileNotFoundError) as e:
            print(f"{name:9s}  skipped: {e}")
            continue
        feats = [ex.extract(seq.load(i)[0]) for i in range(len(seq))]
        glue = LightGlueMatcher(name) if args.lightglue and name in WEIGHTS else None
        size = seq.cameras[0].width, seq.cameras[0].height
        gate_d = gate.max_distance_binary if ex.binary else gate.max_distance_float
        label = name + ("+LG" if glue is not None else "")
        todo = pairs or [(i, i + step) for step in args.steps for i in range(len(seq) - step)]
        counts = {}  # (i, j) -> (keypoints of i, matches, correct matches)
        for i, j in todo:
            a, b = feats[i], feats[j]
            if glue is not None:
                ia, ib = glue(a["keypoints"], a["descriptors"], size, b["keypoints"], b["descriptors"], size)
            else:
                ia, ib = match_knn_ratio(a["descriptors"], b["descriptors"], ex.binary, gate_d, gate.ratio)
            T_21 = np.linalg.inv(T_wc[j]) @ T_wc[i]
            ok = correct_matches(a["keypoints"][ia], b["keypoints"][ib], depths[i], K, T_21)
            counts[i, j] = len(a["keypoints"]), len(ia), int(ok.sum())
        for i, j in pairs:
            n, m, ok = counts[i, j]
            dist = np.linalg.norm(T_wc[i][:3, 3] - T_wc[j][:3, 3])
            print(f"{label:9s}  {i}:{j} ({dist:.2f} m apart)  keypoints {n}  matches {m}  correct {ok}")
        for step in [] if pairs else args.steps:
            r = np.array([counts[i, i + step] for i in range(len(seq) - step)], float)
            print(f"{label:9s}  {step:4d}  {np.median(r[:, 0]):9.0f}  {np.median(r[:, 1]):7.0f}  "
                  f"{np.median(r[:, 2]):15.0f}  {np.percentile(r[:, 2], 10):3.0f}  {np.mean(r[:, 2] >= 30):11.0%}  "
                  f"{np.mean(r[:, 2] >= 50):11.0%}  {np.median(r[:, 2] / np.maximum(r[:, 1], 1)):12.2f}")


if __name__ == "__main__":
    main()
