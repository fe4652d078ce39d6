"""`run(sequence, extractor, cfg) -> SLAMTrajectory`: the SLAM over a sequence, plus the TUM writer.

The pipeline order lives here: tracking, then for each new keyframe local mapping and then loop closing.
Synchronous mode (default, used by tests): keyframes are processed inline and every RANSAC is seeded, so a run is
reproducible. Threaded mode: the same processing in a worker thread (`keyframe_pipeline.py`), bundle adjustment in
a child process (`solver_process.py`). Bad frames (unreadable, black, featureless) are skipped with a warning and
tracking resumes; a sequence that never initialises returns an empty trajectory with a warning, never a traceback.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from ruslam.data.readers import FrameReadError, Trajectory, write_tum_trajectory
from ruslam.models.feature_matching import match_knn_ratio
from ruslam.slam.atlas import Atlas
from ruslam.slam.bundle_adjustment import bundle_adjustment
from ruslam.slam.conditioning import ImageConditioning
from ruslam.slam.geometry import epipolar_mask, fundamental_from_poses, project, triangulate
from ruslam.slam.keyframe_pipeline import KeyframePipeline, ThreadedKeyframePipeline
from ruslam.slam.local_mapping import LocalMapper, MappingConfig
from ruslam.slam.loop_closing import LoopCloser, LoopConfig
from ruslam.slam.map import Frame, inverse_pose
from ruslam.slam.solver_process import SolverProcess
from ruslam.slam.tracking import Tracker, TrackingConfig

log = logging.getLogger(__name__)


@dataclass
class SLAMConfig:
    sensor: str = "auto"  # "mono", "stereo", or "auto" (stereo when the sequence has two cameras)
    synchronous: bool = True
    mapping_backlog: int = 1  # threaded mode: keyframes queued or being mapped before the tracker waits for them
    solver_process: bool = True  # threaded mode: bundle adjustment in a child process (gtsam holds the GIL)
    prefetch: bool = True  # load and extract the next frame in a background thread while this one is tracked
    # (OpenCV and torch release the GIL; the same results, it only uses the second core)
    blas_threads: int | None = 1  # numpy/scipy/OpenCV BLAS threads during the run (None: leave as is); the SLAM's
    # matrices are small, and OpenBLAS threads that spin for a busy core made a run 2.5x slower (BENCHMARKS.md)
    seed: int = 0
    progress: bool = True
    max_frames: int | None = None
    stereo_epipolar_px: float = 2.0
    stereo_max_depth_baselines: float = 80.0
    conditioning: ImageConditioning = field(default_factory=ImageConditioning)  # first step: e.g. CLAHE
    pair_matcher: Any = None  # a learned two-image matcher for initialisation, the tracking fallbacks and
    # relocalisation (`ruslam.models.lightglue.LightGlueMatcher`); None: nearest neighbours + ratio test everywhere
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)


@dataclass
class SLAMTrajectory:
    """Poses T_world_cam0 [N, 4, 4] of the tracked frames, plus what the run did."""

    timestamps: np.ndarray
    poses: np.ndarray
    frame_indices: np.ndarray  # index in the sequence of each pose
    num_frames: int
    timings: np.ndarray  # [num_frames] seconds per frame (extraction + tracking + inline mapping)
    num_keyframes: int = 0
    num_points: int = 0
    loops: list = field(default_factory=list)  # (frame index, loop frame index) of each closed loop
    merges: list = field(default_factory=list)  # (frame index, frame index in the other map) of each map merge
    bridges: list = field(default_factory=list)  # (frame index, last tracked frame index) of each loss bridged by
    # two-view geometry (a weak link, in the same map)
    map_frames: list = field(default_factory=list)  # frames with a pose in each final map, largest first
    initialized_at: int | None = None  # index of the frame at which the first map was initialised

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def tracked_ratio(self) -> float:
        """Share of the frames in the reported trajectory (the largest map; other maps' frames do not count)."""
        return len(self) / max(self.num_frames, 1)

    @property
    def num_maps(self) -> int:
        return len(self.map_frames)

    def write_tum(self, path: str | Path) -> None:
        write_tum(path, self.timestamps, self.poses)


def write_tum(path: str | Path, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """TUM format ``timestamp tx ty tz qx qy qz qw`` (`ruslam.data.readers.write_tum_trajectory`)."""
    write_tum_trajectory(path, Trajectory(timestamps, poses))


def as_config(cfg) -> SLAMConfig:
    """SLAMConfig from None (defaults), a SLAMConfig, or a Hydra/dict config with `_target_`s."""
    if cfg is None:
        return SLAMConfig()
    if isinstance(cfg, SLAMConfig):
        return cfg
    from hydra.utils import instantiate  # noqa: PLC0415 (only configs need hydra)

    out = instantiate(cfg)
    if not isinstance(out, SLAMConfig):
        raise TypeError(f"SLAM config must build a SLAMConfig (`_target_: ruslam.slam.system.SLAMConfig`), "
                        f"got {type(out).__name__}.")
    return out


def make_frame(index, timestamp, images, extractor, sequence, stereo: bool, cfg: SLAMConfig) -> Frame | None:
    """Extract features (both cameras in stereo), undistort them, and triangulate stereo matches."""
    cam0 = sequence.cameras[0]
    out = extractor.extract(images[0])
    kps = cam0.undistort_points(out["keypoints"]) if len(out["keypoints"]) else np.zeros((0, 2))
    if len(kps) < cfg.tracking.min_keypoints:
        log.warning("Frame %d skipped: %d keypoints found, the minimum is %d (tracking.min_keypoints).", index,
                    len(kps), cfg.tracking.min_keypoints)
        return None
    g = out.get("global_descriptor")
    frame = Frame(index=index, timestamp=float(timestamp), keypoints=kps.astype(np.float64),
                  descriptors=out["descriptors"], K=cam0.K, image_size=(cam0.width, cam0.height),
                  global_descriptor=None if g is None else np.asarray(g, np.float32),
                  scales=None if out.get("scales") is None else np.asarray(out["scales"], np.float64))
    if stereo:
        cam1 = sequence.cameras[1]
        out_r = extractor.extract(images[1])
        kps_r = cam1.undistort_points(out_r["keypoints"]) if len(out_r["keypoints"]) else np.zeros((0, 2))
        frame.right = np.full((len(kps), 2), np.nan)
        frame.depth = np.full(len(kps), np.nan)
        if len(kps_r) == 0:
            return frame
        T_c1_c0 = inverse_pose(np.asarray(sequence.T_cam0_cam1, np.float64))
        mask = epipolar_mask(fundamental_from_poses(cam0.K, cam1.K, T_c1_c0), kps, kps_r, cfg.stereo_epipolar_px)
        t = cfg.tracking
        a, b = match_knn_ratio(out["descriptors"], out_r["descriptors"], extractor.binary,
                               t.max_distance_binary if extractor.binary else t.max_distance_float, t.ratio,
                               mutual=True, mask=mask)
        X = triangulate(cam0.K, np.eye(4), kps[a], cam1.K, T_c1_c0, kps_r[b])
        u0, z0 = project(cam0.K, np.eye(4), X)
        u1, z1 = project(cam1.K, T_c1_c0, X)
        baseline = np.linalg.norm(T_c1_c0[:3, 3])
        ok = (z0 > 0) & (z1 > 0) & (z0 < cfg.stereo_max_depth_baselines * baseline)
        ok &= (np.sum((u0 - kps[a]) ** 2, 1) < 4) & (np.sum((u1 - kps_r[b]) ** 2, 1) < 4)
        frame.right[a[ok]] = kps_r[b[ok]]
        frame.depth[a[ok]] = z0[ok]
    return frame


def run(sequence, extractor, cfg=None) -> SLAMTrajectory:
    """Run the SLAM over `sequence` (ruslam.data.readers.Sequence) with any extractor of the project contract."""
    cfg = as_config(cfg)
    if isinstance(extractor, str):
        from ruslam.models.registry import load_extractor  # noqa: PLC0415

        extractor = load_extractor(extractor)
    stereo = _sensor(sequence, cfg.sensor)
    binary = bool(getattr(extractor, "binary", False))
    rig = (sequence.cameras[1].K, np.asarray(sequence.T_cam0_cam1, np.float64)) if stereo else None
    atlas = Atlas()
    n = len(sequence) if cfg.max_frames is None else min(len(sequence), cfg.max_frames)
    timings = np.zeros(n)
    skipped = 0
    initialized_at = None
    with ExitStack() as cleanup:  # undone in reverse order, also when a constructor below raises
        solver = None
        if not cfg.synchronous and cfg.solver_process:
            solver = cleanup.enter_context(closing(SolverProcess(cfg.blas_threads)))
        cleanup.enter_context(threadpool_limits(cfg.blas_threads, user_api="blas"))  # torch's threads are not BLAS
        mapper = LocalMapper(atlas, cfg.mapping, binary, rig, solver or bundle_adjustment)
        loop_closer = LoopCloser(atlas, mapper, cfg.loop, binary, stereo, cfg.seed, cfg.pair_matcher)

        def process_keyframe(kf) -> None:  # local mapping, then loop closing on what it mapped
            if mapper.process(kf):
                loop_closer.process(kf)

        keyframes = (KeyframePipeline(process_keyframe) if cfg.synchronous else
                     ThreadedKeyframePipeline(process_keyframe, solver.interrupt if solver is not None else None))
        cleanup.callback(keyframes.finish)
        tracker = Tracker(atlas, keyframes, mapper.bundle_adjust, loop_closer.database, cfg.tracking, binary, rig,
                          cfg.seed, cfg.pair_matcher)
        frames = cleanup.enter_context(closing(_frames(n, sequence, extractor, stereo, cfg)))
        for i in tqdm(range(n), desc=f"SLAM {getattr(sequence, 'name', '')}", disable=not cfg.progress):
            start = time.perf_counter()
            frame = next(frames)
            keyframes.catch_up(cfg.mapping_backlog)  # after the extraction, which overlaps the mapper's work
            if frame is None:
                skipped += 1
            elif tracker.track(frame):
                initialized_at = i if initialized_at is None else initialized_at
                if tracker.initial_frame is not None:  # the first frame of a monocular initialisation
                    kf1, tracker.initial_frame = tracker.initial_frame, None
                    atlas.record(kf1.index, kf1.timestamp, kf1, kf1.T_cw)
                atlas.record(i, frame.timestamp, tracker.reference, frame.T_cw)
            timings[i] = time.perf_counter() - start
        keyframes.catch_up(0)  # the map is final: the frames between and before initial keyframes are posed on it
        for frame, reference in tracker.pose_untracked():
            atlas.record(frame.index, frame.timestamp, reference, frame.T_cw)
    records, poses, map_frames = atlas.trajectory()
    if not records:
        log.warning("SLAM on %s: no frame was tracked (initialisation never succeeded on %d frames, %d skipped).",
                    getattr(sequence, "name", "sequence"), n, skipped)
    elif len(map_frames) > 1:
        log.warning("SLAM on %s: %d maps that never merged (frames with a pose per map: %s); the trajectory is the "
                    "largest one.", getattr(sequence, "name", "sequence"), len(map_frames), map_frames)
    final = records[0].reference.map.resolved() if records else atlas.active
    return SLAMTrajectory(
        timestamps=np.array([r.timestamp for r in records], np.float64), poses=poses,
        frame_indices=np.array([r.index for r in records], int), num_frames=n, timings=timings,
        num_keyframes=len(final.keyframes), num_points=len(final.points), loops=list(loop_closer.loops),
        merges=list(loop_closer.merges), bridges=list(tracker.bridges), map_frames=map_frames,
        initialized_at=initialized_at,
    )


def _sensor(sequence, sensor: str) -> bool:
    """True for stereo; validates that the sequence can serve the requested sensor."""
    if sensor not in ("auto", "mono", "stereo"):
        raise ValueError(f"SLAM sensor must be 'auto', 'mono' or 'stereo', got {sensor!r}.")
    cams = len(sequence.cameras)
    if sensor == "stereo" and (cams < 2 or sequence.T_cam0_cam1 is None):
        raise ValueError(f"Stereo SLAM needs two cameras and T_cam0_cam1; sequence "
                         f"{getattr(sequence, 'name', '')!r} has {cams} camera(s).")
    if len(sequence) == 0:
        raise ValueError(f"Sequence {getattr(sequence, 'name', '')!r} has no frames.")
    return sensor == "stereo" or (sensor == "auto" and cams >= 2 and sequence.T_cam0_cam1 is not None)


def _frames(n, sequence, extractor, stereo, cfg):
    """Frames 0..n-1 (None for a skipped one); with `cfg.prefetch`, frame i + 1 is made in a worker thread while
    frame i is tracked."""
    if not cfg.prefetch:
        for i in range(n):
            yield _load_frame(i, sequence, extractor, stereo, cfg)
        return
    with ThreadPoolExecutor(1, thread_name_prefix="ruslam-frames") as pool:
        pending = pool.submit(_load_frame, 0, sequence, extractor, stereo, cfg)
        try:
            for i in range(n):
                frame = pending.result()
                if i + 1 < n:
                    pending = pool.submit(_load_frame, i + 1, sequence, extractor, stereo, cfg)
                yield frame
        finally:  # stopped early (an error in tracking): a frame not yet started is not made
            pending.cancel()


def _load_frame(i, sequence, extractor, stereo, cfg) -> Frame | None:
    """Frame i, or None (with a warning) when it cannot be read or has too few features."""
    try:
        images = sequence.load(i)
    except FrameReadError as err:  # the one expected condition: a missing or undecodable frame file
        log.warning("Frame %d skipped: %s", i, err)
        return None
    images = [cfg.conditioning(image) for image in images]
    return make_frame(i, sequence.timestamps[i], images, extractor, sequence, stereo, cfg)
