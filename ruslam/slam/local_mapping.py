"""Local mapping (paper 3.1): keyframe insertion, covisibility update, point culling, new points by triangulation
with neighbours, fusion of duplicates, local bundle adjustment (`bundle_adjustment.py`, Huber) and
redundant-keyframe culling.

`LocalMapper.process` is synchronous; `keyframe_pipeline.py` runs it inline or in a worker thread, followed by loop
closing (`system.run` sets that order).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ruslam.models.feature_matching import (
    descriptor_distances,
    match_in_windows,
    match_knn_ratio,
    paired_distances,
)
from ruslam.slam.atlas import Atlas
from ruslam.slam.bundle_adjustment import SOLVERS, bundle_adjustment
from ruslam.slam.geometry import (
    CHI2_2DOF,
    epipolar_mask,
    fundamental_from_poses,
    triangulate,
    triangulation_mask,
)
from ruslam.slam.map import KeyFrame, Map, PointStore, inverse_pose, transform, update_descriptors, update_normals

log = logging.getLogger(__name__)


@dataclass
class MappingConfig:
    max_distance_binary: float = 64.0
    max_distance_float: float = 0.5
    ratio: float = 0.8
    sigma_binary: float = 1.0  # keypoint noise (px), as TrackingConfig
    sigma_float: float = 1.0
    triangulation_neighbours: int = 10
    epipolar_px: float = 4.0
    min_parallax_deg: float = 1.0
    max_distance_ratio: float = 1.8  # of a new point's distances to the two keyframes
    fuse_neighbours: int = 10
    fuse_radius: float = 3.0
    ba_keyframes: int = 7  # optimised keyframes (the new one and its best covisible neighbours)
    ba_fixed_keyframes: int = 5  # other keyframes seeing local points, held fixed
    ba_iterations: tuple[int, int] = (3, 4)  # LM iterations before / after dropping outlier observations
    ba_solver: str = "schur"  # numpy, gtsam's LM steps, 2-3x faster, GIL released; or "gtsam" (the reference)
    redundancy: float = 0.9  # cull a keyframe when this share of its points is seen by >= 3 others
    min_found_ratio: float = 0.25  # cull a new point matched in fewer than this share of frames that could see it

    def __post_init__(self):
        if self.ba_solver not in SOLVERS:  # here, not at the first local BA after initialisation
            raise ValueError(f"mapping.ba_solver must be one of {SOLVERS}, got {self.ba_solver!r}.")


class LocalMapper:
    def __init__(self, atlas: Atlas, cfg: MappingConfig, binary: bool, rig=None,
                 solve: Callable[..., tuple] = bundle_adjustment):
        # solve: `bundle_adjustment`, or the same call in a child process (`solver_process.SolverProcess`)
        self.atlas, self.cfg, self.binary, self.rig, self.solve = atlas, cfg, binary, rig, solve
        self.max_distance = cfg.max_distance_binary if binary else cfg.max_distance_float
        self.sigma = cfg.sigma_binary if binary else cfg.sigma_float
        self.recent: list[int] = []  # ids of points made in the last keyframes, culled early if rarely found

    @property
    def map(self) -> Map:
        """The active map: keyframes of a map left behind (tracking lost) are not mapped any further."""
        return self.atlas.active

    @property
    def store(self) -> PointStore:
        return self.atlas.store

    # --- one keyframe ------------------------------------------------------------------------------------------
    def process(self, kf: KeyFrame) -> bool:
        """Map one keyframe; False when it no longer belongs to the active map (culled, or its map left behind)."""
        with self.atlas.lock:
            if kf.is_bad or kf.map is not self.map:
                return False
            self._insert(kf)
            self._cull_points(kf)
            self._triangulate(kf)
            self._fuse(kf)
            problem = self._local_ba_problem(kf) if len(self.map.keyframes) > 2 else None
        if problem is not None:
            # solved outside the lock: a threaded tracker goes on meanwhile (with a solver process or the numpy
            # solver, which release the GIL); what it changes (new keyframes, counters) is not in the problem, and
            # the write-back re-checks
            solution = self._solve(problem, self.cfg.ba_iterations)
            with self.atlas.lock:
                self._write_back(problem, solution)
                self._cull_keyframes(kf)
        return True

    def _insert(self, kf: KeyFrame) -> None:
        s = self.store
        observed = []  # points this keyframe newly observes
        matched = kf.points >= 0
        matched[matched] = ~s.bad[kf.points[matched]]
        kf.points[~matched] = -1
        for i in np.nonzero(matched)[0]:
            j = int(kf.points[i])
            if kf not in s.observations[j]:
                s.add_observation(j, kf, int(i))
                observed.append(j)
            else:  # created by this keyframe (stereo points)
                self.recent.append(j)
        update_normals(s, observed)
        update_descriptors(s, observed, self.binary)
        self.map.update_connections(kf)

    def _cull_points(self, kf: KeyFrame) -> None:
        min_obs = 3 if self.rig is not None else 2
        s = self.store
        keep = []
        for j in self.recent:
            age = kf.id - s.first_kf_id[j]
            if s.bad[j] or s.reference[j].map.resolved() is not kf.map:  # a point of a map left behind
                continue
            if s.found[j] / max(s.visible[j], 1) < self.cfg.min_found_ratio or \
                    (age >= 2 and len(s.observations[j]) < min_obs):
                self.map.remove_point(j)
            elif age < 3:
                keep.append(j)
        self.recent = keep

    # --- new points --------------------------------------------------------------------------------------------
    def _triangulate(self, kf: KeyFrame) -> None:
        c = self.cfg
        K = kf.K
        s = self.store
        free1 = kf.points < 0
        neighbours = self.map.neighbours(kf, c.triangulation_neighbours)
        # widest baseline first: a keypoint is triangulated with the most distant neighbour that sees it
        neighbours.sort(key=lambda n: -np.linalg.norm(n.center - kf.center))
        for n in neighbours:
            baseline = np.linalg.norm(n.center - kf.center)
            if self.rig is not None:
                if baseline < np.linalg.norm(self.rig[1][:3, 3]):
                    continue
            else:
                seen = s.alive(n.points)
                if not len(seen):
                    continue
                depth = np.median(transform(n.T_cw, s.position[seen])[:, 2])
                if baseline / max(depth, 1e-9) < 0.01:
                    continue
            i1 = np.nonzero(free1)[0]
            i2 = np.nonzero(n.points < 0)[0]
            if len(i1) == 0 or len(i2) == 0:
                continue
            F = fundamental_from_poses(K, n.K, n.T_cw @ inverse_pose(kf.T_cw))
            mask = epipolar_mask(F, kf.keypoints[i1], n.keypoints[i2], c.epipolar_px)
            a, b = match_knn_ratio(kf.descriptors[i1], n.descriptors[i2], self.binary, self.max_distance, c.ratio,
                                   mutual=True, mask=mask)
            a, b = i1[a], i2[b]
            keep = self._distinct_from_mapped(kf, n, F, a, b)
            a, b = a[keep], b[keep]
            X = triangulate(K, kf.T_cw, kf.keypoints[a], n.K, n.T_cw, n.keypoints[b])
            ok = triangulation_mask(X, K, kf.T_cw, kf.keypoints[a], n.K, n.T_cw, n.keypoints[b],
                                    max_error_px=np.sqrt(CHI2_2DOF) * self.sigma, min_parallax_deg=c.min_parallax_deg)
            # single-scale keypoints: the two viewing distances must be alike (ORB-SLAM's scale check, one octave)
            ratio = np.linalg.norm(X - n.center, axis=1) / np.maximum(np.linalg.norm(X - kf.center, axis=1), 1e-9)
            ok &= (ratio < c.max_distance_ratio) & (ratio > 1.0 / c.max_distance_ratio)
            rays = [X[ok] - c for c in (kf.center, n.center)]
            normals = sum(r / np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12) for r in rays)
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            new = []
            for ia, ib, x in zip(a[ok], b[ok], X[ok], strict=True):
                j = self.map.new_point(x, kf.descriptors[ia], kf)
                s.add_observation(j, kf, int(ia))
                s.add_observation(j, n, int(ib))
                new.append(j)
                free1[ia] = False
            s.set_normals(np.array(new, np.int64), normals)
            self.recent += new

    def _distinct_from_mapped(self, kf: KeyFrame, n: KeyFrame, F: np.ndarray, a: np.ndarray, b: np.ndarray):
        """[len(a)] bool: the match kf[a] <-> n[b] of free keypoints also passes the ratio test and the mutual check
        against the keypoints on its epipolar lines that already observe map points. Repetitive texture (tiles) puts
        look-alikes on those lines: where the right match is mapped already, a free look-alike would be triangulated
        at its own depth, and the map's scale would follow it."""
        keep = np.ones(len(a), bool)
        if not len(a):
            return keep
        best = paired_distances(kf.descriptors[a], n.descriptors[b], self.binary)
        mapped1, mapped2 = np.nonzero(kf.points >= 0)[0], np.nonzero(n.points >= 0)[0]
        if len(mapped2):  # a mapped rival of kf[a] in n, within the ratio test's reach
            d = descriptor_distances(kf.descriptors[a], n.descriptors[mapped2], self.binary)
            d[~epipolar_mask(F, kf.keypoints[a], n.keypoints[mapped2], self.cfg.epipolar_px)] = np.inf
            keep &= best < self.cfg.ratio * d.min(axis=1)
        if len(mapped1):  # a mapped keypoint of kf nearer to n[b] (its mutual nearest neighbour)
            d = descriptor_distances(kf.descriptors[mapped1], n.descriptors[b], self.binary)
            d[~epipolar_mask(F, kf.keypoints[mapped1], n.keypoints[b], self.cfg.epipolar_px)] = np.inf
            keep &= best <= d.min(axis=0)
        return keep

    def _fuse(self, kf: KeyFrame) -> None:
        targets = []
        for n in self.map.neighbours(kf, self.cfg.fuse_neighbours):
            for m in [n, *self.map.neighbours(n, 5)]:
                if m is not kf and m not in targets:
                    targets.append(m)
        s = self.store
        for t in targets:
            self.fuse_points(t, s.alive(kf.points))
        if targets:
            self.fuse_points(kf, s.seen_by(targets))
        points = s.alive(kf.points)
        update_descriptors(s, points, self.binary)
        update_normals(s, points)
        self.map.update_connections(kf)

    def fuse_points(self, kf: KeyFrame, points: np.ndarray, T_cw: np.ndarray | None = None,
                    replace_with_new: bool = False) -> int:
        """Project points (ids) into kf and merge each with the point already at the matched keypoint (or add it).

        `T_cw` overrides kf's pose (loop fusion with the corrected similarity). Returns the number of fusions.
        """
        s = self.store
        points = np.array([j for j in points if not s.bad[j] and kf not in s.observations[j]], np.int64)
        if not len(points):
            return 0
        X = s.position[points]
        T = kf.T_cw if T_cw is None else T_cw
        Xc = transform(T, X)
        z = Xc[:, 2]
        uv = Xc[:, :2] / np.where(z > 1e-9, z, 1e-9)[:, None] @ kf.K[:2, :2].T + kf.K[:2, 2]
        vis = np.nonzero((z > 0) & kf.in_image(uv))[0]
        if len(vis) == 0:
            return 0
        ip, ik = match_in_windows(uv[vis], s.descriptor[points[vis]], kf.keypoints, kf.descriptors,
                                  self.cfg.fuse_radius, self.binary, self.max_distance, ratio=1.0)
        fused = 0
        for j, k in zip(points[vis[ip]].tolist(), ik.tolist(), strict=True):
            if s.bad[j] or kf in s.observations[j]:
                continue
            q = int(kf.points[k])
            if q >= 0 and not s.bad[q]:
                if replace_with_new or len(s.observations[j]) > len(s.observations[q]):
                    self.map.replace_point(q, j)
                else:
                    self.map.replace_point(j, q)
            else:
                s.add_observation(j, kf, k)
            fused += 1
        return fused

    # --- bundle adjustment -------------------------------------------------------------------------------------
    def _local_ba_problem(self, kf: KeyFrame) -> dict | None:
        c = self.cfg
        local = [kf, *self.map.neighbours(kf, c.ba_keyframes - 1)]
        points = self.store.seen_by(local)
        outside: dict[KeyFrame, int] = {}
        local_set = set(local)
        for j in points:
            for k in self.store.observations[j]:
                if k not in local_set and not k.is_bad:
                    outside[k] = outside.get(k, 0) + 1
        fixed = sorted(outside, key=lambda k: (-outside[k], k.id))[: c.ba_fixed_keyframes]
        first = self.map.keyframes[0]
        if first in local_set and self.rig is None:  # the first keyframe anchors the monocular gauge
            local.remove(first)
            fixed.insert(0, first)
        kfs = local + fixed
        return self._ba_problem(kfs, np.arange(len(kfs)) >= len(local), points)

    def bundle_adjust(self, kfs: list[KeyFrame], fixed: np.ndarray, points: np.ndarray, iterations) -> None:
        """BA over keyframes/points; writes back poses, positions, and drops outlier observations."""
        problem = self._ba_problem(kfs, fixed, points)
        if problem is not None:
            self._write_back(problem, self._solve(problem, iterations))

    def _ba_problem(self, kfs: list[KeyFrame], fixed: np.ndarray, points: np.ndarray) -> dict | None:
        """The arrays of a BA (`ruslam.slam.bundle_adjustment`) over keyframes and point ids, to write back."""
        if not len(points) or len(kfs) < 2:
            return None
        kidx = {k: i for i, k in enumerate(kfs)}
        # one row per observation by a problem keyframe, in the points' order (then, for a stereo keyframe with a
        # right measurement, a second row right after it)
        observations = [self.store.observations[j] for j in points]
        counts = [len(o) for o in observations]
        flat = np.array([(kidx.get(k, -1), i) for o in observations for k, i in o.items()], int).reshape(-1, 2)
        owner = np.repeat(np.arange(len(points)), counts)
        inside = flat[:, 0] >= 0
        flat, owner = flat[inside], owner[inside]
        rep = np.ones(len(flat), int)
        if self.rig is not None:
            for a, k in enumerate(kfs):
                sel = np.nonzero(flat[:, 0] == a)[0]
                if k.right is not None and len(sel):
                    rep[sel] += np.isfinite(k.right[flat[sel, 1], 0])
        rows = np.repeat(np.arange(len(flat)), rep)
        orr = np.zeros(len(rows), bool)
        orr[1:] = rows[1:] == rows[:-1]  # the second row of a pair is the right camera's
        owner = owner[rows]
        # a point seen once (without a stereo measurement) has no depth: leave it out, it would stall LM
        keep = np.bincount(owner, minlength=len(points)) >= 2
        if not keep.any():
            return None
        sel = keep[owner]
        rows, orr, owner = rows[sel], orr[sel], owner[sel]
        oi, ok = flat[rows, 0], flat[rows, 1]
        oj = (np.cumsum(keep) - 1)[owner]
        points = points[keep]
        uv = np.empty((len(oi), 2))
        for a, k in enumerate(kfs):
            for right, pixels in ((False, k.keypoints), (True, k.right)):
                sel = (oi == a) & (orr == right)
                if sel.any():
                    uv[sel] = pixels[ok[sel]]
        return {"kfs": kfs, "points": points, "fixed": np.asarray(fixed, bool), "oi": oi, "oj": oj, "uv": uv,
                "right": orr, "poses": np.array([k.T_cw for k in kfs]),
                "positions": self.store.position[points]}

    def _solve(self, problem: dict, iterations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        K_r, T_c0_c1 = (self.rig[0], self.rig[1]) if self.rig is not None else (None, None)
        q = problem
        return self.solve(q["poses"], q["fixed"], q["positions"], q["oi"], q["oj"], q["uv"], q["kfs"][0].K,
                          q["right"], K_r, T_c0_c1, iterations=tuple(iterations), sigma=self.sigma,
                          solver=self.cfg.ba_solver)

    def _write_back(self, problem: dict, solution) -> None:
        poses, pts, inl = solution
        kfs, points, oi, oj = problem["kfs"], problem["points"], problem["oi"], problem["oj"]
        for k, T, f in zip(kfs, poses, problem["fixed"], strict=True):
            if not f:
                k.T_cw = T
        s = self.store
        s.position[points] = pts
        for a, j in {(int(a), int(j)) for a, j in zip(oi[~inl], oj[~inl], strict=True)}:
            k, observations = kfs[a], s.observations[points[j]]
            if k in observations:
                k.points[observations.pop(k)] = -1
                if len(observations) < 2:
                    k.map.resolved().remove_point(points[j])  # the problem's map (tracking may have started a new one)

    # --- keyframe culling --------------------------------------------------------------------------------------
    def _cull_keyframes(self, kf: KeyFrame) -> None:
        s = self.store
        for n in self.map.neighbours(kf):
            if n is self.map.keyframes[0] or n is kf or n.loop_edges:
                continue
            pts = s.alive(n.points)
            if self.rig is not None and n.depth is not None:
                pts = [j for j in pts if np.isfinite(n.depth[s.observations[j][n]])]
            if len(pts) < 20:
                continue
            redundant = sum(1 for j in pts if len(s.observations[j]) - 1 >= 3)
            if redundant > self.cfg.redundancy * len(pts):
                self.map.remove_keyframe(n)
