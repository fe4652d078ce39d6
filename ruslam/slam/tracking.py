"""Tracking (paper 3.3): initialisation, motion model, fallbacks, local-map tracking, keyframes, recovery.

A frame is first searched in windows around the constant-velocity prediction (then a window twice as wide); when that
fails, matched by descriptor to the last frame's points (the closest view in a fast turn), then to the reference
keyframe's (kNN + ratio, pose from the last one or PnP), then to the whole local map by descriptor without any window
(PnP RANSAC: the pose of a fast turn is unknown, so no prior is trusted); each pose these give is a hypothesis that the
local map must confirm, and one it refuses passes the frame to the next method. A monocular fallback's pose also fits
the epipolar geometry of its matches to the last frame, which a map with the wrong relief does not hold (a turn taken
for sideways travel). Where none of them posed the frame, a learned pair matcher (LightGlue) matches the last frame,
then the reference keyframe, once more. When all fail, the frame is bridged to the last tracked frame by two-view
geometry in the same map (monocular); when that fails too the tracker is lost: it relocalises against the active map
(the latest keyframes and, with a global descriptor, retrieval) and tries the bridge again for `lost_frames` frames,
then starts a new map in the Atlas (ORB-SLAM3); while that map initialises it keeps trying to relocalise in the map it
lost. Loop closing merges the maps when they meet again.

The Tracker holds no threads: it hands keyframes to `keyframes.insert_keyframe(kf)` and asks `keyframes.idle()`
(`keyframe_pipeline.py`: inline or queued to a worker thread).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import numpy as np

from ruslam.models.feature_matching import descriptor_distances, match_in_windows, match_knn_ratio
from ruslam.slam.atlas import Atlas
from ruslam.slam.geometry import (
    CHI2_1DOF,
    CHI2_2DOF,
    epipolar_mask,
    fundamental_from_poses,
    solve_pnp_ransac,
    step_min_parallax_deg,
    two_view_initialization,
)
from ruslam.slam.map import Frame, KeyFrame, Map, PointStore, inverse_pose, scale_translation, transform, update_normals
from ruslam.slam.optimization import optimize_pose, sampson

log = logging.getLogger(__name__)


@dataclass
class TrackingConfig:
    max_distance_binary: float = 64.0  # Hamming bits (of 256) for ORB
    window_distance_binary: float = 100.0  # ORB inside a projection window (ORB-SLAM's TH_HIGH): the window
    # constrains the match; 64 there lost the real pool run's tiles (BENCHMARKS.md)
    max_distance_float: float = 0.5  # L2 between unit descriptors (0..2); XFeat: correct 0.2-0.46, wrong 0.3-0.5
    # (0.7 let enough wrong matches through that XFeat lost track at 3x the embedded speed, see README)
    ratio: float = 0.8  # kNN ratio test
    sigma_binary: float = 1.0  # keypoint noise (px): Huber width and chi2 outlier test scale with it
    sigma_float: float = 1.0  # learned extractors (1.5, for XFeat's heavier error tail, let wrong matches bias poses)
    window_ratio: float = 0.8  # ratio test inside a search window (0.9 let XFeat's look-alike neighbours through)
    window_radius: float = 15.0  # px, constant-velocity search (doubled on failure), times the keypoint's pyramid scale
    window_rivals: float = 2.0  # its ratio test against look-alikes up to this many radii away: in repetitive
    # texture (tiles, a checkerboard) the window may hold only a copy one period off the point (BENCHMARKS.md)
    local_map_radius: float = 5.0  # px, local-map search
    min_inliers: int = 30  # tracked map points for a frame to count as tracked
    init_min_matches: int = 100
    init_window: float = 100.0  # px, monocular initialisation search window
    init_max_frames: int = 40  # restart initialisation from a newer frame after this many (a 20 Hz start: 2 s)
    max_untracked: int = 300  # untracked frames kept for posing around a later initialisation at the end of the
    # run (`pose_untracked`): ~1 MB each with a learned extractor's descriptors
    init_min_parallax_deg: float = 1.0
    init_sigma_float: float = 1.5  # px, H-vs-F scoring of float keypoints (at 1.0 the degenerate F of a flat floor
    # won in Jerlov 3C on DEV hard and started the map 23-48 deg off)
    min_keypoints: int = 50  # fewer (black / featureless frame): skip the frame
    kf_max_frames: int = 10  # a keyframe is due after this many frames (if tracking has weakened at all) ...
    kf_min_frames: int = 3  # ... and allowed after this many, like ORB-SLAM's "mapping is idle" (see _need_keyframe)
    kf_urgent_ratio: float = 0.5  # below this share of the reference's points a keyframe is inserted at once
    kf_min_tracked: int = 150  # ... and below this many tracked points (fast motion: new points before the map ends)
    kf_ratio_mono: float = 0.9  # tracked points / reference keyframe points below which a keyframe is needed
    kf_ratio_stereo: float = 0.75
    stereo_close_baselines: float = 40.0  # stereo points closer than this many baselines count as "close"
    local_keyframes: int = 20
    reloc_candidates: int = 5
    lost_frames: int = 3  # failed relocalisations (and bridges) before a new map is started
    bridge: bool = True  # lost: the motion from the last tracked frame by two-view geometry, in the same map
    local_map_fallback: bool = True  # last fallback: the local map by descriptor + PnP RANSAC
    last_frame_fallback: bool = True  # first fallback: the last frame's points by descriptor (fast turns)
    two_view_constraints: bool = True  # a fallback's pose also fits its epipolar geometry to the last frame


class Tracker:
    def __init__(self, atlas: Atlas, keyframes, bundle_adjust, database, cfg: TrackingConfig, binary: bool, rig=None,
                 seed: int = 0, pair_matcher=None):
        # keyframes: the KeyframePipeline; bundle_adjust: LocalMapper.bundle_adjust (the initial map's BA);
        # pair_matcher: a learned two-image matcher (e.g. LightGlue) for initialisation, the descriptor fallbacks and
        # relocalisation, where nearest neighbours alone find too few matches; None = kNN + ratio test
        self.atlas, self.keyframes, self.bundle_adjust, self.database = atlas, keyframes, bundle_adjust, database
        self.pair_matcher = pair_matcher
        self.cfg = cfg
        self.binary, self.rig, self.seed = binary, rig, seed  # rig: (K_right, T_c0_c1) for stereo
        self.max_distance = cfg.max_distance_binary if binary else cfg.max_distance_float
        self.window_distance = cfg.window_distance_binary if binary else cfg.max_distance_float
        self.sigma = cfg.sigma_binary if binary else cfg.sigma_float
        self.noise_radius = np.sqrt(CHI2_2DOF) * self.sigma  # px: keypoints closer than this are one location
        self.state = "init"
        self.init_frame: Frame | None = None
        self.last: Frame | None = None
        self.last_ref: tuple[KeyFrame, np.ndarray, float] | None = None  # (reference kf, T_last_ref, its scale)
        self.velocity: np.ndarray | None = None  # in the scale of last_ref
        self.lost_count = 0
        self.speed = 0.0  # map units per second over the last step (a bridge's scale when no point is shared)
        self.step_dt = 0.0  # seconds the last step took
        self.bridges: list[tuple[int, int]] = []  # (frame index, bridged-from frame index): the weak links
        self.bridge_from: Frame | None = None  # the last tracked frame of the active map
        self.lost_map: Map | None = None  # the map tracking was lost in, while a new one initialises
        self.reference: KeyFrame | None = None
        self.last_kf_index = -10**9
        self.initial_frame: KeyFrame | None = None  # set when monocular initialisation also poses an older frame
        self.untracked: deque[Frame] = deque(maxlen=cfg.max_untracked)  # since the last tracked frame
        # per initialisation: its keyframes (one for stereo) and the untracked frames before and between them
        self.initialisations: list[tuple[list[KeyFrame], list[Frame], list[Frame]]] = []
        self.two_view: tuple | None = None  # `_two_view_matches`: a fallback's matches to the last frame

    @property
    def map(self) -> Map:
        return self.atlas.active

    @property
    def store(self) -> PointStore:
        return self.atlas.store

    # --- entry point -------------------------------------------------------------------------------------------
    def track(self, frame: Frame) -> bool:
        """Estimate `frame.T_cw`; True when the frame is tracked against the (active) map."""
        with self.atlas.lock:
            bridged = False
            if self.state == "init":
                back = self._back_in_lost_map(frame) if self.lost_map is not None else None
                if back is not None:
                    bridged = back == "bridged"
                    ok = bridged or self._track_local_map(frame)
                else:
                    ok = self._initialize_stereo(frame) if self.rig is not None else self._initialize_mono(frame)
                    if not ok:
                        self.untracked.append(frame)
                        return False
                    self.state, self.lost_map = "ok", None
                    initial = self.map.keyframes[:1 if self.rig is not None else 2]
                    self.initialisations.append((
                        initial, [f for f in self.untracked if f.index < initial[0].index],
                        [f for f in self.untracked if initial[0].index < f.index < initial[-1].index]))
                    self.untracked.clear()
                    return True
            elif self.state == "ok":
                ok = self._track_frame(frame)
            else:
                ok = self._relocalize(frame, self.map) and self._track_local_map(frame)
            bridged = bridged or (not ok and self._bridge(frame))
            if not ok and not bridged:
                self._lost(frame)
                self.untracked.append(frame)
                return False
            self.state, self.lost_count = "ok", 0
            self.untracked.clear()
            if self.last is not None and self.last.T_cw is not None:
                self.velocity = frame.T_cw @ inverse_pose(self.last.T_cw)
                dt = frame.timestamp - self.last.timestamp
                if dt > 0:
                    self.speed, self.step_dt = float(np.linalg.norm(self.velocity[:3, 3])) / dt, dt
            self._drop_outliers(frame)
            if not bridged and self._need_keyframe(frame):
                self._insert_keyframe(frame)
                # inline mapping may have moved the new keyframe (local BA, a loop correction, a map merge): the
                # frame is that keyframe, so it takes its pose (a stale one left a 1.3 m spike at every loop)
                frame.T_cw = self.reference.pose().copy()
            self.last = self.bridge_from = frame
            self.last_ref = (self.reference, frame.T_cw @ inverse_pose(self.reference.T_cw),
                             self.reference.current_scale())
            return True

    # --- bridging a loss ---------------------------------------------------------------------------------------
    def _bridge(self, frame: Frame) -> bool:
        """Tracking and relocalisation failed: pose `frame` from the last tracked frame by two-view geometry (E or H,
        chosen as in initialisation) and keep both as keyframes of the same map, with points triangulated between
        them. Scale: the depths of the map points seen in both views where they agree (`_map_scale`), else the last
        speed. A weak link: local BA, later loops and merges refine it. False (a lost frame) when two-view geometry
        fails too."""
        prev = self.bridge_from
        if not self.cfg.bridge or self.rig is not None or prev is None or self.last_ref is None:
            return False
        ref, T_lr, scale = self.last_ref
        if ref.map.resolved() is not self.map:
            return False
        prev.T_cw = scale_translation(T_lr, ref.current_scale() / scale) @ ref.pose()  # after BA, loops, merges
        prev.points = self.store.resolve(prev.points)
        c = self.cfg
        prior = self.velocity[:3, :3] if self.velocity is not None and self.last is prev else None
        out, tried = None, []
        for ia, ib, guided in self._bridge_matches(prev, frame):
            tried.append((ia, ib))
            out = self._bridge_motion(prev, frame, ia, ib, c.min_inliers, guided, prior)
            if out is not None:
                break
        else:  # every match set failed: a motion with half the points, confirmed along its epipolar lines
            for ia, ib in tried:
                out = self._bridge_motion(prev, frame, ia, ib, c.min_inliers // 2, True, prior)
                if out is not None:
                    break
        if out is None:
            log.debug("Frame %d: no bridge from frame %d (two-view geometry failed).", frame.index, prev.index)
            return False
        T21, X, good, model = out  # X in prev's camera frame, unit median depth
        ia, ib, X = ia[good], ib[good], X[good]
        shared = prev.points[ia]
        has = (shared >= 0) & ~self.store.bad[np.maximum(shared, 0)]
        s = map_scale = self._map_scale(prev, shared[has], X[has])
        if map_scale is None:
            s = self._speed_scale(prev, T21, X, frame.timestamp - prev.timestamp)
        if not (np.isfinite(s) and s > 0):
            return False
        kf_prev = ref if ref.index == prev.index and not ref.is_bad else None
        if kf_prev is None:
            kf_prev = self.map.new_keyframe(prev)
            self.keyframes.insert_keyframe(kf_prev)  # mapped (inline, or queued) before the bridged keyframe
        frame.T_cw = scale_translation(T21, s) @ kf_prev.pose()
        frame.clear_points()
        frame.outliers[:] = False
        frame.points[ib[has]] = shared[has]
        T_wp = inverse_pose(kf_prev.pose())
        new = []
        for a, b, x in zip(ia[~has], ib[~has], X[~has], strict=True):
            if kf_prev.points[a] >= 0:
                continue
            j = self.map.new_point(T_wp[:3, :3] @ (s * x) + T_wp[:3, 3], frame.descriptors[b], kf_prev)
            self.store.add_observation(j, kf_prev, int(a))
            frame.points[b] = j
            new.append(j)
        update_normals(self.store, new)
        kf = self.map.new_keyframe(frame)
        self.reference = kf
        self.last_kf_index = frame.index
        self.keyframes.insert_keyframe(kf)
        frame.T_cw = kf.pose().copy()
        frame.points = self.store.resolve(kf.points.copy())
        self.bridges.append((frame.index, prev.index))
        log.info("Frame %d: tracking lost; bridged from frame %d by two-view geometry (%s, %d points, %s scale).",
                 frame.index, prev.index, model, len(ia), "speed" if map_scale is None else "map")
        return True

    def _speed_scale(self, prev: Frame, T21: np.ndarray, X: np.ndarray, dt: float) -> float:
        """A bridge's scale from the last speed. Across dropped frames the camera either kept that speed (a rendered
        lap's 8 dropped frames) or made only about its last step (the pool crawler stopped while frames were lost):
        between those two steps, the one that puts the new points (X, prev's frame) at the median depth of the map
        points prev tracked."""
        lo, hi = sorted((self.speed * dt, self.speed * self.step_dt))
        t = float(np.linalg.norm(T21[:3, 3]))
        tracked = prev.points[prev.points >= 0]
        tracked = tracked[~self.store.bad[tracked]]
        step = hi
        if lo < hi and len(tracked):
            depth = np.median(transform(prev.T_cw, self.store.position[tracked])[:, 2])
            step = float(np.clip(depth / np.median(X[:, 2]) * t, lo, hi))
        return step / max(t, 1e-12)

    def _map_scale(self, prev: Frame, points: np.ndarray, X: np.ndarray) -> float | None:
        """A bridge's scale from the map's depths of `points` (seen in both views; X: their two-view positions): the
        median ratio of map to two-view depth, when 10 points give it and the middle half of their ratios spans at
        most half the median. Points that disagree (the map's depths of a few weak points) set the step 7x off on the
        TUM circle; None: the last speed scales the step."""
        if len(points) < 10:
            return None
        ratios = transform(prev.T_cw, self.store.position[points])[:, 2] / X[:, 2]
        q1, median, q3 = np.percentile(ratios, [25, 50, 75])
        return float(median) if q3 - q1 <= 0.5 * median else None

    def _bridge_motion(self, prev: Frame, frame: Frame, ia, ib, min_points: int, confirm: bool, prior):
        """The two-view motion prev -> frame from matches ia <-> ib that triangulates `min_points` points, or None;
        with `confirm`, only when distinctive matches along its epipolar lines confirm it (`_distinctive_along`)."""
        c = self.cfg
        if len(ia) < min_points:
            return None
        out = two_view_initialization(prev.keypoints[ia], frame.keypoints[ib], frame.K, self.seed + frame.index,
                                      step_min_parallax_deg(frame.K, self.sigma), min_points,
                                      sigma=self.sigma if self.binary else c.init_sigma_float, prior_R=prior, step=True)
        if out is not None and confirm and self._distinctive_along(out[0], prev, frame) < c.min_inliers // 2:
            log.debug("Frame %d: bridge from frame %d refused: too few distinctive matches along its epipolar lines.",
                      frame.index, prev.index)
            return None
        return out

    def _bridge_matches(self, prev: Frame, frame: Frame):
        """Match sets for a bridge, cheapest first, each with whether its motion must be confirmed by distinctive
        matches (`_distinctive_along`): kNN + ratio; mutual nearest neighbours alone (repetitive texture, tiles,
        fails the ratio test; RANSAC sorts the matches), confirmed; the pair matcher if there is one."""
        everything = np.arange(len(prev))
        yield *self._match_knn(prev, everything, frame), False
        yield *match_knn_ratio(prev.descriptors, frame.descriptors, self.binary, self.max_distance, 1.0), True
        if self.pair_matcher is not None:
            yield *self._match_pair(prev, everything, frame), False

    def _distinctive_along(self, T21: np.ndarray, prev: Frame, frame: Frame) -> int:
        """Matches that pass the ratio test among the keypoints within 2 sigma of their epipolar line under the
        motion T21. A true motion confines each match to a band where it stands out (ORB on the pool's 13 s gap:
        39, from 167 mutual nearest neighbours; XFeat across an 8-frame blackout of a rendered lap: 33); look-alike
        texture in views that do not overlap fits a motion whose bands hold no such matches (8 of 2,000)."""
        band = epipolar_mask(fundamental_from_poses(frame.K, frame.K, T21), prev.keypoints, frame.keypoints,
                             2.0 * (self.sigma if self.binary else self.cfg.init_sigma_float))
        return len(match_knn_ratio(prev.descriptors, frame.descriptors, self.binary, self.max_distance,
                                   self.cfg.ratio, mask=band)[0])

    def _lost(self, frame: Frame) -> None:
        """One more failed frame; after `lost_frames` of them, a new map (the old one stays in the Atlas)."""
        frame.T_cw = None
        self.velocity = self.last = None
        if self.state == "ok":
            log.info("Frame %d: tracking lost.", frame.index)
        self.state = "lost"
        self.lost_count += 1
        if self.lost_count < self.cfg.lost_frames:
            return
        log.info("Frame %d: relocalisation failed for %d frames; starting a new map.", frame.index,
                 self.lost_count)
        self.lost_map = self.map
        self.atlas.new_map()
        self.state, self.lost_count, self.init_frame = "init", 0, None
        self.reference = None
        if self.rig is None and len(frame) >= self.cfg.init_min_matches:
            frame.clear_points()
            self.init_frame = frame  # the reference of the new map's initialisation

    def _back_in_lost_map(self, frame: Frame) -> str | None:
        """While a new map initialises: back to the lost map if the frame relocalises there or, failing that, is bridged
        from its last tracked frame (a loss that outlasted `lost_frames`, e.g. frames with no usable view, ending where
        two views overlap again). "relocalised", "bridged", or None when neither."""
        lost = self.lost_map
        if lost.merged_into is not None or not lost.keyframes:
            self.lost_map = None
            return None
        how = "relocalised" if self._relocalize(frame, lost) else None
        if how is None:
            new, self.atlas.active = self.atlas.active, lost  # a bridge adds its keyframes to the active map
            how = "bridged" if self._bridge(frame) else None
            self.atlas.active = new
        if how is None:
            return None
        log.info("Frame %d: back in map %d (%s); the new map is dropped.", frame.index, lost.id, how)
        self.atlas.activate(lost)  # drops the new map, still empty
        self.state, self.lost_map, self.init_frame = "ok", None, None
        return how

    # --- initialisation ----------------------------------------------------------------------------------------
    def _initialize_stereo(self, frame: Frame) -> bool:
        if frame.depth is None or np.sum(np.isfinite(frame.depth)) < self.cfg.init_min_matches:
            return False
        frame.T_cw = np.eye(4)
        kf = self.map.new_keyframe(frame)
        self._add_stereo_points(kf, all_points=True)
        frame.points = kf.points.copy()
        self._start(frame, kf, [kf])
        return True

    def _initialize_mono(self, frame: Frame) -> bool:
        c = self.cfg
        ref = self.init_frame
        if ref is None or frame.index - ref.index > c.init_max_frames:
            self._new_init_reference(frame)
            return False
        ip, ik = match_in_windows(ref.keypoints, ref.descriptors, frame.keypoints, frame.descriptors, c.init_window,
                                  self.binary, self.max_distance, c.window_ratio)
        # a wide baseline (or a fast turn) moves points beyond the window: kNN over the whole image, then the pair
        # matcher (learned, 0.5-1.5 s a pair on one core) if even that finds too few
        for match in self._matchers():
            if len(ip) < c.init_min_matches:
                jp, jk = match(ref, np.arange(len(ref)), frame)
                if len(jp) > len(ip):
                    ip, ik = jp, jk
        if len(ip) < c.init_min_matches:  # too little overlap left: this frame is the next reference (ORB-SLAM)
            self._new_init_reference(frame)
            return False
        out = two_view_initialization(ref.keypoints[ip], frame.keypoints[ik], frame.K, self.seed + frame.index,
                                      c.init_min_parallax_deg, c.init_min_matches // 2,
                                      sigma=self.sigma if self.binary else c.init_sigma_float)
        if out is None:
            return False
        T2, X, good, model = out
        ref.T_cw, frame.T_cw = np.eye(4), T2
        kf1, kf2 = self.map.new_keyframe(ref), self.map.new_keyframe(frame)
        for a, b, x in zip(ip[good], ik[good], X[good], strict=True):
            j = self.map.new_point(x, frame.descriptors[b], kf1)
            self.store.add_observation(j, kf1, int(a))
            self.store.add_observation(j, kf2, int(b))
        self.bundle_adjust([kf1, kf2], np.array([True, False]), self.map.sorted_points(), (10, 10))
        seen = kf1.points[kf1.points >= 0]
        median = float(np.median(transform(kf1.T_cw, self.store.position[seen])[:, 2])) if len(seen) else 0.0
        if median <= 0 or np.count_nonzero(kf2.points >= 0) < c.init_min_matches // 2:
            log.warning("Frame %d: monocular initialisation rejected after bundle adjustment.", frame.index)
            self._reset()
            return False
        self.store.position[list(self.map.points)] /= median  # unit median depth, as ORB-SLAM
        kf2.T_cw[:3, 3] /= median
        frame.T_cw = kf2.T_cw.copy()
        frame.points = kf2.points.copy()
        log.info("Initialised (%s) from frames %d and %d with %d points.", model, ref.index, frame.index,
                 len(self.map.points))
        self._start(frame, kf2, [kf1, kf2])
        dt = frame.timestamp - ref.timestamp
        self.speed = float(np.linalg.norm(kf2.T_cw[:3, 3])) / dt if dt > 0 else 0.0  # a bridge's scale at once
        self.step_dt = dt
        self.initial_frame = kf1
        return True

    def _new_init_reference(self, frame: Frame) -> None:
        self.init_frame = frame if len(frame) >= self.cfg.init_min_matches else None

    def pose_untracked(self) -> list[tuple[Frame, KeyFrame]]:
        """Poses, on the final map, for the untracked frames around each initialisation, tracked as forwards but
        without new keyframes: the frames between two monocular initial keyframes from the first (those left, back
        from the second), the frames before the first backwards from it (a start the initialisation could not use:
        the camera still, turning, or on a blank view). (frame, reference keyframe) pairs.

        At the end, not at the initialisation: the local BAs after it change the map's scale (2.5x at TEST
        `pitch60`), and a pose recorded then against the fixed first keyframe put the frame 0.35 m off."""
        out = []
        active = self.atlas.active
        for initial, before, between in self.initialisations:
            posed = self._track_from(initial[0], between)
            out += posed + self._track_from(initial[-1], between[len(posed):][::-1])
            out += self._track_from(initial[0], before[::-1])
        self.atlas.active = active
        return out

    def _track_from(self, kf: KeyFrame, frames: list[Frame]) -> list[tuple[Frame, KeyFrame]]:
        """`frames` tracked in turn from keyframe `kf` on the final map, until one fails."""
        out = []
        if kf.is_bad or not frames:
            return out
        self.atlas.active = kf.map.resolved()  # the run is over: the local map is taken from kf's map
        self.reference = kf
        self.last = Frame(kf.index, kf.timestamp, kf.keypoints, kf.descriptors, kf.K, kf.image_size, scales=kf.scales,
                          T_cw=kf.pose().copy(), points=self.store.resolve(kf.points))
        self.last_ref, self.velocity = (kf, np.eye(4), kf.current_scale()), None
        for f in frames:
            f.clear_points()
            if not self._track_frame(f):
                break
            self._drop_outliers(f)
            out.append((f, self.reference))
            self.velocity = f.T_cw @ inverse_pose(self.last.T_cw)
            self.last = f
            self.last_ref = (self.reference, f.T_cw @ inverse_pose(self.reference.T_cw), self.reference.current_scale())
        return out

    def _reset(self) -> None:
        for kf in list(self.map.keyframes):
            kf.is_bad = True
        self.map.keyframes.clear()
        self.map.points.clear()
        self.map.covisibility.clear()
        self.init_frame = None

    def _start(self, frame: Frame, kf: KeyFrame, kfs: list[KeyFrame]) -> None:
        self.reference = kf
        self.last = self.bridge_from = frame
        self.last_ref = (kf, frame.T_cw @ inverse_pose(kf.T_cw), kf.current_scale())
        self.last_kf_index = frame.index
        self.velocity = None
        for k in kfs:
            self.keyframes.insert_keyframe(k)

    # --- frame-to-frame ----------------------------------------------------------------------------------------
    def _track_frame(self, frame: Frame) -> bool:
        """The first nearest-neighbour pose hypothesis (`_pose_hypotheses`) that the local map confirms: ORB-SLAM
        tracks the local map after its motion model or reference keyframe and is lost when that fails; here a refused
        pose (a look-alike match, a stale reference) hands the frame to the next method. Only where none of them
        posed the frame, the pair matcher's first pose (last frame, then reference keyframe) is tried: where nearest
        neighbours match but the map refuses their poses, a bridge builds new geometry instead."""
        posed = False
        for how in self._pose_hypotheses(frame):
            posed = True
            if self._confirmed(frame, how):
                return True
        if posed or self.pair_matcher is None:
            return False
        for name, ref, use in (("last frame", self.last, self.cfg.last_frame_fallback),
                               ("reference keyframe", self.reference, True)):
            if use and self._track_by_descriptor(frame, ref, self._match_pair):
                return self._confirmed(frame, f"{name} by descriptor (pair matcher)")
        return False

    def _confirmed(self, frame: Frame, how: str) -> bool:
        """The local map's verdict on the pose `how` gave the frame (logged)."""
        if self._track_local_map(frame):
            log.debug("Frame %d: %s.", frame.index, how)
            return True
        log.debug("Frame %d: %s, refused by the local map (%d inliers).", frame.index, how,
                  int(np.count_nonzero(frame.points >= 0) - frame.outliers.sum()))
        return False

    def _pose_hypotheses(self, frame: Frame):
        """Poses of `frame` by nearest-neighbour matching, cheapest first: the motion model's windows; the last
        frame's, the reference keyframe's and the local map's points by descriptor. Each is yielded (its name) with
        frame.T_cw and frame.points set."""
        ref, T_lr, scale = self.last_ref
        ratio = ref.current_scale() / scale  # a loop or a merge may have rescaled the map since the last frame
        self.last.T_cw = scale_translation(T_lr, ratio) @ ref.pose()  # the reference may have moved too
        if self.velocity is not None:
            predicted = scale_translation(self.velocity, ratio) @ self.last.T_cw
            pts = self.store.resolve(self.last.points)
            seen = pts >= 0
            pts = pts[seen]
            # ORB-SLAM's windows: wider for a point the last frame saw on a coarser pyramid level
            pyramid = 1.0 if self.last.scales is None else self.last.scales[seen]
            for base in (self.cfg.window_radius, 2 * self.cfg.window_radius):
                frame.T_cw = predicted.copy()  # the wider windows around the prediction, not the failed optimum
                frame.clear_points()
                radius = base * pyramid
                self._search_points(frame, pts, radius, rival_radius=self.cfg.window_rivals * radius)
                if np.count_nonzero(frame.points >= 0) >= 20 and self._optimize(frame) >= 10:
                    yield f"motion model, {base:g} px windows"
                    break
        self.two_view = self._two_view_matches(frame) if self.cfg.two_view_constraints and self.rig is None else None
        if self.cfg.last_frame_fallback and self._track_by_descriptor(frame, self.last, self._match_knn):
            yield "last frame by descriptor"
        if self._track_by_descriptor(frame, self.reference, self._match_knn):
            yield "reference keyframe by descriptor"
        if self.cfg.local_map_fallback and self._track_local_map_by_descriptor(frame):
            yield "local map by descriptor"

    def _two_view_matches(self, frame: Frame) -> tuple | None:
        """(frame, the last frame's pixels, frame's, their motion T21, each match's noise in sigmas) for the fallbacks'
        pose optimisation (`_optimize`): where the motion model missed, the map's relief alone let a turn pass for
        sideways travel (TUM's cabinet: XFeat's poses a median 3.6 deg off per frame). The motion of the distinctive
        matches (kNN + ratio) as a bridge finds it (H or E, a plane's twin refused by the motion prior; None without the
        points or the parallax), then every mutual nearest neighbour on its epipolar geometry (guided matching; on tiles
        mutual neighbours alone fit a look-alike's motion)."""
        prev = self.last
        sigma = self.sigma if self.binary else self.cfg.init_sigma_float
        d = descriptor_distances(prev.descriptors, frame.descriptors, self.binary)
        ia, ib = match_knn_ratio(prev.descriptors, frame.descriptors, self.binary, self.max_distance, self.cfg.ratio,
                                 distances=d.copy())
        prior = self.velocity[:3, :3] if self.velocity is not None else None
        out = two_view_initialization(prev.keypoints[ia], frame.keypoints[ib], frame.K, self.seed + frame.index,
                                      step_min_parallax_deg(frame.K, self.sigma), self.cfg.min_inliers, sigma=sigma,
                                      prior_R=prior, step=True)
        if out is None:
            return None
        T21 = out[0]
        ia, ib = match_knn_ratio(prev.descriptors, frame.descriptors, self.binary, self.max_distance, 1.0, distances=d)
        x1, x2 = prev.keypoints[ia], frame.keypoints[ib]
        noise = np.ones(len(ia)) if frame.scales is None else np.hypot(prev.scales[ia], frame.scales[ib]) / np.sqrt(2)
        keep = (sampson(T21, x1, x2, frame.K) / noise) ** 2 < CHI2_1DOF * sigma**2  # each at its pyramid levels' noise
        return (frame, x1[keep], x2[keep], T21, noise[keep]) if keep.sum() >= 8 else None

    def _track_local_map_by_descriptor(self, frame: Frame) -> bool:
        """Last fallback: the local map's points matched by descriptor, no window, pose by PnP RANSAC."""
        local = [self.reference, *self.map.neighbours(self.reference, self.cfg.local_keyframes)]
        points = self.store.seen_by(local)
        if len(points) < 15:
            return False
        ia, ib = match_knn_ratio(self.store.descriptor[points], frame.descriptors, self.binary, self.max_distance,
                                 self.cfg.ratio)
        if len(ia) < 15:
            return False
        frame.clear_points()
        return self._pnp(frame, points[ia], ib)

    def _track_by_descriptor(self, frame: Frame, ref: Frame, match) -> bool:
        """Fallback: `ref`'s map points matched by `match` (kNN + ratio, or the pair matcher) in `frame` (ref: the
        last frame, the closest view in a fast turn; the reference keyframe), then the pose by PnP RANSAC (from the
        last pose if that fails). PnP comes first: in a turn the last pose is several degrees off, and from there
        noisy matches (ORB on low-contrast texture) pulled the pose optimisation into a wrong minimum that the map
        then kept (DEV lowtex, BENCHMARKS.md)."""
        frame.clear_points()
        resolved = self.store.resolve(ref.points)
        idx = np.nonzero(resolved >= 0)[0]
        if len(idx) == 0:
            return False
        ia, ib = match(ref, idx, frame)
        if len(ia) < 15:
            return False
        points = resolved[idx[ia]]
        if self._pnp(frame, points, ib):
            return True
        frame.points[ib] = points
        frame.T_cw = self.last.T_cw.copy()
        return self._optimize(frame) >= 10

    # Matching ref's keypoints idx to `frame` without a pose: -> (positions in idx, keypoints of frame)
    def _matchers(self) -> list:
        """kNN + ratio first; the pair matcher (if any) only when that fails, so easy frames pay nothing for it."""
        return [self._match_knn] + ([self._match_pair] if self.pair_matcher is not None else [])

    def _match_knn(self, ref: Frame, idx: np.ndarray, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        return match_knn_ratio(ref.descriptors[idx], frame.descriptors, self.binary, self.max_distance,
                               self.cfg.ratio)

    def _match_pair(self, ref: Frame, idx: np.ndarray, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """All keypoints matched by the learned matcher (the context it was trained with), then those in idx kept."""
        ia, ib = self.pair_matcher(ref.keypoints, ref.descriptors, ref.image_size, frame.keypoints,
                                   frame.descriptors, frame.image_size)
        position = np.full(len(ref), -1)
        position[idx] = np.arange(len(idx))
        keep = position[ia] >= 0
        return position[ia[keep]], ib[keep]

    def _pnp(self, frame: Frame, points: np.ndarray, kp_idx: np.ndarray) -> bool:
        """Pose of `frame` from map point ids matched to its keypoints `kp_idx`, by PnP RANSAC."""
        out = solve_pnp_ransac(self.store.position[points], frame.keypoints[kp_idx], frame.K,
                               seed=self.seed + frame.index)
        if out is None:
            return False
        frame.T_cw, inliers = out
        frame.clear_points()
        frame.points[kp_idx[inliers]] = points[inliers]
        return self._optimize(frame) >= 10

    # --- local map ---------------------------------------------------------------------------------------------
    def _track_local_map(self, frame: Frame) -> bool:
        """The local map's points searched around the frame's pose, which they refine; True at `min_inliers`. Only a
        confirmed pose becomes the reference and counts for the points (visible in its view, found)."""
        counts: dict[KeyFrame, int] = {}
        observations = self.store.observations
        for j in self.store.alive(frame.points):
            for kf in observations[j]:
                counts[kf] = counts.get(kf, 0) + 1
        if not counts:
            return False
        local = sorted(counts, key=lambda k: -counts[k])[: self.cfg.local_keyframes]
        for kf in list(local):
            for n in self.map.neighbours(kf, 10):
                if n not in counts and len(local) < 2 * self.cfg.local_keyframes:
                    counts[n] = 0
                    local.append(n)
        seen = self.store.seen_by(local)  # up to 40 keyframes' points
        candidates = seen[~np.isin(seen, frame.points)]
        in_view = self._search_points(frame, candidates, self.cfg.local_map_radius)
        inliers = self._optimize(frame)
        log.debug("Frame %d: local map, %d inliers of %d matches.", frame.index, inliers,
                  np.count_nonzero(frame.points >= 0))
        if inliers < self.cfg.min_inliers:
            return False
        self.reference = local[0]
        np.add.at(self.store.visible, in_view, 1)
        np.add.at(self.store.found, frame.points[(frame.points >= 0) & ~frame.outliers], 1)
        return True

    def _search_points(self, frame: Frame, points: np.ndarray, radius, rival_radius=None) -> np.ndarray:
        """Project map points (ids) with frame.T_cw and match them in windows of `radius` px (scalar or per point);
        returns the ids of those in view."""
        if not len(points):
            return points
        X = self.store.position[points]
        uv, z = frame.project(X)
        centre = frame.center
        rays = X - centre
        dist = np.linalg.norm(rays, axis=1)
        normals = self.store.normal[points]
        cos = np.sum(rays * normals, 1) / np.maximum(dist, 1e-12)
        visible = (z > 0) & frame.in_image(uv) & ((cos > 0.5) | (np.abs(normals).sum(1) == 0))
        vis = np.nonzero(visible)[0]
        if np.ndim(radius):
            radius, rival_radius = radius[vis], rival_radius if np.ndim(rival_radius) == 0 else rival_radius[vis]
        ip, ik = match_in_windows(uv[vis], self.store.descriptor[points[vis]], frame.keypoints, frame.descriptors,
                                  radius, self.binary, self.window_distance, self.cfg.window_ratio,
                                  available=frame.points < 0, distinct_px=self.noise_radius,
                                  rival_radius=rival_radius)
        frame.points[ik] = points[vis[ip]]
        return points[vis]

    def _optimize(self, frame: Frame) -> int:
        """Motion-only pose optimisation over the frame's matches; returns the number of inliers."""
        idx = np.nonzero(frame.points >= 0)[0]
        frame.outliers = np.zeros(len(frame), bool)
        if len(idx) < 6:
            return 0
        X = self.store.position[frame.points[idx]]
        uv_r = frame.right[idx] if self.rig is not None and frame.right is not None else None
        K_r, T_c1_c0 = (self.rig[0], inverse_pose(self.rig[1])) if self.rig is not None else (None, None)
        epipolar = None
        if self.two_view is not None and self.two_view[0] is frame:
            # the two-view motion (its twin on a plane refused by the motion prior) at the pose's step length: from
            # PnP's pose the optimisation could settle in the twin, where the map's points on the plane fit too
            _, x1, x2, T21, noise = self.two_view
            epipolar = (self.last.T_cw, x1, x2, noise)
            step = np.linalg.norm((frame.T_cw @ inverse_pose(self.last.T_cw))[:3, 3])
            frame.T_cw = scale_translation(T21, step / np.linalg.norm(T21[:3, 3])) @ self.last.T_cw
        T, inl = optimize_pose(frame.T_cw, X, frame.keypoints[idx], frame.K, uv_r, K_r, T_c1_c0, sigma=self.sigma,
                               epipolar=epipolar)
        frame.T_cw = T
        frame.outliers[idx[~inl]] = True
        return int(inl.sum())

    def _drop_outliers(self, frame: Frame) -> None:
        frame.points[frame.outliers] = -1
        frame.outliers[:] = False

    # --- keyframes ---------------------------------------------------------------------------------------------
    def _need_keyframe(self, frame: Frame) -> bool:
        c = self.cfg
        since = frame.index - self.last_kf_index
        min_obs = 2 if len(self.map.keyframes) <= 2 else 3
        ref_ids = self.reference.points[self.reference.points >= 0]
        ref_points = int(np.count_nonzero(self.store.num_observations(ref_ids) >= min_obs))
        tracked = int(np.count_nonzero(frame.points >= 0))
        ratio = c.kf_ratio_stereo if self.rig is not None else c.kf_ratio_mono
        need_close = False
        if self.rig is not None and frame.depth is not None:
            close = frame.depth < c.stereo_close_baselines * np.linalg.norm(self.rig[1][:3, 3])
            has = frame.points >= 0
            need_close = np.sum(close & has) < 100 and np.sum(close & ~has) > 70
        weak = tracked < ratio * ref_points or need_close
        # ORB-SLAM inserts when local mapping is idle; run inline, mapping is always idle and every frame would
        # become a keyframe, so "idle" also needs kf_min_frames since the last one (or very weak tracking)
        idle = self.keyframes.idle()
        if weak and not idle and since >= c.kf_min_frames:
            self.keyframes.interrupt()
        allowed = since >= c.kf_max_frames or (idle and since >= c.kf_min_frames)
        urgent = tracked < c.kf_urgent_ratio * ref_points or tracked < c.kf_min_tracked
        return bool((allowed and weak or urgent) and tracked > 15)

    def _insert_keyframe(self, frame: Frame) -> None:
        kf = self.map.new_keyframe(frame)
        if self.rig is not None:
            self._add_stereo_points(kf, all_points=False)
        self.reference = kf
        self.last_kf_index = frame.index
        self.keyframes.insert_keyframe(kf)

    def _add_stereo_points(self, kf: KeyFrame, all_points: bool) -> None:
        """ORB-SLAM's close stereo points: new map points from stereo depth for unmatched keypoints."""
        if kf.depth is None:
            return
        free = (kf.points < 0) & np.isfinite(kf.depth)
        idx = np.nonzero(free)[0]
        idx = idx[np.argsort(kf.depth[idx], kind="stable")]
        if not all_points:
            limit = self.cfg.stereo_close_baselines * np.linalg.norm(self.rig[1][:3, 3])
            idx = idx[(kf.depth[idx] < limit) | (np.arange(len(idx)) < 100)]
        Kinv = np.linalg.inv(kf.K)
        T_wc = inverse_pose(kf.T_cw)
        new = []
        for i in idx:
            xc = Kinv @ np.r_[kf.keypoints[i], 1.0] * kf.depth[i]
            j = self.map.new_point(T_wc[:3, :3] @ xc + T_wc[:3, 3], kf.descriptors[i], kf)
            self.store.add_observation(j, kf, int(i))
            new.append(j)
        update_normals(self.store, new)

    # --- relocalisation ----------------------------------------------------------------------------------------
    def _relocalize(self, frame: Frame, in_map: Map) -> bool:
        """Candidates: the latest keyframes of `in_map`, then global-descriptor retrieval in it; kNN (then the pair
        matcher) + PnP."""
        candidates = in_map.keyframes[-self.cfg.reloc_candidates:][::-1]
        if frame.global_descriptor is not None and self.database is not None and len(self.database):
            candidates += self.database.query(frame.global_descriptor, self.cfg.reloc_candidates, set(candidates),
                                              maps=[in_map])
        for match in self._matchers():  # every candidate by kNN first, then by the pair matcher
            for kf in candidates:
                idx = self.store.matched(kf)
                if len(idx) < 15:
                    continue
                ia, ib = match(kf, idx, frame)
                if len(ia) < 15:
                    continue
                frame.clear_points()
                if not self._pnp(frame, kf.points[idx[ia]], ib):
                    continue
                self._search_points(frame, self.store.alive(kf.points), 10.0)
                if self._optimize(frame) >= 50:
                    log.info("Frame %d relocalised against keyframe %d.", frame.index, kf.id)
                    self.reference = kf
                    return True
        frame.T_cw = None
        return False
