"""Chained two-view visual odometry: the baseline a monocular SLAM is compared against.

Each frame is matched to the last posed one (mutual nearest neighbours; kNN + ratio test when RANSAC finds no
model among those, as on repeated tiles), its relative pose comes from E or H (the model chosen as in initialisation,
`geometry.two_view_initialization`, the last rotation as prior), and the length of each step is carried over by the
points it shares with the step before (their depths in the common frame). No map, no bundle adjustment, no loop
closure. A frame whose geometry holds with too little parallax to fix a step waits (the camera hardly moved): it is
posed by interpolation once a later frame makes the step. A frame whose geometry fails is skipped; after
`tracking.lost_frames` skipped frames, or when a frame no longer overlaps the last posed one, a new segment starts
(reported like a new map).
"""

from __future__ import annotations

import time
from contextlib import closing

import numpy as np

from ruslam.models.feature_matching import match_knn_ratio
from ruslam.slam.geometry import interpolate_pose, step_min_parallax_deg, two_view_initialization
from ruslam.slam.map import inverse_pose, scale_translation, transform
from ruslam.slam.system import SLAMTrajectory, _frames, as_config


def run(sequence, extractor, cfg=None) -> SLAMTrajectory:
    """Poses of `sequence` by chained two-view geometry, with the SLAM's extraction settings (`cfg`: SLAMConfig)."""
    cfg = as_config(cfg)
    t = cfg.tracking
    binary = bool(getattr(extractor, "binary", False))
    max_distance = t.max_distance_binary if binary else t.max_distance_float
    sigma = t.sigma_binary if binary else t.init_sigma_float
    n = len(sequence) if cfg.max_frames is None else min(len(sequence), cfg.max_frames)
    timings = np.zeros(n)
    posed: list[tuple[int, float, np.ndarray]] = []  # (frame index, timestamp, T_cw)
    segments: list[int] = []
    last = None  # (frame, T_cw, {keypoint index: depth in that frame}, rotation of the last step, speed)
    waiting: list = []  # frames since the last posed one whose geometry lacked only parallax
    with closing(_frames(n, sequence, extractor, False, cfg)) as frames:
        for i in range(n):
            start = time.perf_counter()
            frame = next(frames)
            if frame is not None:
                last = _step(last, frame, cfg.seed, binary, max_distance, t, sigma, posed, segments, waiting)
            timings[i] = time.perf_counter() - start
    poses = np.array([inverse_pose(T) for _, _, T in posed]).reshape(-1, 4, 4)
    # the reported trajectory is the longest segment, as the SLAM reports its largest map
    ends = np.cumsum(segments)
    k = int(np.argmax(segments)) if segments else 0
    sel = slice(ends[k] - segments[k], ends[k]) if segments else slice(0, 0)
    return SLAMTrajectory(
        timestamps=np.array([ts for _, ts, _ in posed[sel]], np.float64), poses=poses[sel],
        frame_indices=np.array([i for i, _, _ in posed[sel]], int), num_frames=n, timings=timings,
        map_frames=sorted(segments, reverse=True), initialized_at=posed[0][0] if posed else None,
    )


def _step(last, frame, seed, binary, max_distance, t, sigma, posed, segments, waiting):
    """Pose `frame` from `last`; returns the new `last` (unchanged when the frame waits or is skipped)."""
    if last is None:
        return _restart(frame, posed, segments, waiting)
    prev, T_prev, depth_prev, R_prior, speed = last
    found = _relative_pose(prev, frame, seed, binary, max_distance, t, sigma, R_prior,
                           step_min_parallax_deg(frame.K, sigma))
    if found is None:
        a, _ = match_knn_ratio(prev.descriptors, frame.descriptors, binary, max_distance, 1.0, mutual=True)
        if len(a) < t.min_inliers // 2:  # no overlap left: a new segment
            return _restart(frame, posed, segments, waiting)
        if _relative_pose(prev, frame, seed, binary, max_distance, t, sigma, R_prior, 0.0) is not None:
            waiting.append(frame)
            return last
        return _restart(frame, posed, segments, waiting) if frame.index - prev.index > t.lost_frames else last
    a, b, (T21, X, good, _) = found
    a, b, X = a[good], b[good], X[good]
    dt = frame.timestamp - prev.timestamp
    known = np.array([depth_prev.get(int(k), np.nan) for k in a])
    shared = np.isfinite(known)
    if not depth_prev:  # the first step of a segment: unit median depth
        scale = 1.0
    elif np.count_nonzero(shared) >= 5:
        scale = float(np.median(known[shared] / X[shared, 2]))
    else:
        scale = speed * dt / max(float(np.linalg.norm(T21[:3, 3])), 1e-12)  # constant speed
    T21 = scale_translation(T21, scale)
    T_cw = T21 @ T_prev
    for f in waiting:  # in time between the two posed frames
        posed.append((f.index, f.timestamp, interpolate_pose(T_prev, T_cw, (f.timestamp - prev.timestamp) / dt)))
    posed.append((frame.index, frame.timestamp, T_cw))
    segments[-1] += len(waiting) + 1
    waiting.clear()
    depth = dict(zip(b.tolist(), transform(T21, scale * X)[:, 2].tolist(), strict=True))
    return frame, T_cw, depth, T21[:3, :3], float(np.linalg.norm(T21[:3, 3])) / max(dt, 1e-9)


def _relative_pose(prev, frame, seed, binary, max_distance, t, sigma, R_prior, min_parallax_deg):
    """(matched keypoints of prev, of frame, two_view_initialization's output) or None; mutual matches first."""
    for ratio in (1.0, t.ratio):
        a, b = match_knn_ratio(prev.descriptors, frame.descriptors, binary, max_distance, ratio, mutual=True)
        out = two_view_initialization(prev.keypoints[a], frame.keypoints[b], frame.K, seed + frame.index,
                                      min_parallax_deg, t.min_inliers, sigma=sigma, prior_R=R_prior, step=True)
        if out is not None:
            return a, b, out
    return None


def _restart(frame, posed, segments, waiting):
    waiting.clear()  # frames that waited on a segment that ends keep no pose
    posed.append((frame.index, frame.timestamp, np.eye(4)))
    segments.append(1)
    return frame, np.eye(4), {}, None, 0.0
