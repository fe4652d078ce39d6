"""Loop closing by global descriptors (paper 3.4).

Keyframes' global descriptors live in one matrix; a query scores them all with eq. 9, ``score = 1 - ||a - b||`` of
the L2-normalised vectors, as one matrix product (``||a-b||^2 = 2 - 2 a.b``). Candidates are the top-k above a
threshold (the larger of a fixed floor and the lowest score of the keyframe's own covisible neighbours, as ORB-SLAM
does with DBoW2), excluding those neighbours; a candidate must be consistent over consecutive keyframes, then pass
geometric verification (descriptor matches + Sim3 RANSAC for monocular, SE3 for stereo, then a guided search; the
learned pair matcher adds matches where kNN finds too few, only when those few already agree on one similarity); the
best-scoring candidate that verifies is closed when its correction does not undo most of the motion between the two
keyframes (`undoes_the_motion`: drift is a fraction of the motion) and either the predicted correction lowers the
map's robust reprojection cost (`_lowers_residuals`) or the keyframes just before verified a loop to the same place,
`consistency` in a row (ORB-SLAM3's three verifications), with a correction that turns the camera by less than half
its field of view (`turns_out_of_view`): the loop is corrected by propagating the similarity to the
covisible group, fusing duplicated points, optimising the essential graph (gtsam Similarity3 / Pose3) and moving
every map point with its reference keyframe. Extractors without a global descriptor (ORB, SIFT) skip loop detection.

Map merging (ORB-SLAM3's Atlas): while the Atlas holds inactive maps, every new keyframe of the active map is also
checked against the last keyframes of each inactive map (the place where tracking was lost) and, with a global
descriptor, against the best-scoring keyframes of the inactive maps; the same geometric verification accepts a
link, and the active map is moved into the inactive one by the similarity (`Atlas.merge`), then welded by fusing
the linked region's points.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ruslam.models.feature_matching import match_in_windows, match_knn_ratio
from ruslam.slam.atlas import Atlas
from ruslam.slam.bundle_adjustment import bundle_adjustment, robust_cost
from ruslam.slam.geometry import pose_matrix, rotation_deg, sim3_ransac
from ruslam.slam.map import KeyFrame, Map, inverse_pose, transform, update_normals
from ruslam.slam.optimization import pose_graph_optimization

log = logging.getLogger(__name__)
STRUCTURE_ITERATIONS = 3  # Levenberg-Marquardt steps of the points (poses held) in the residual check


@dataclass
class LoopConfig:
    enabled: bool = True
    top_k: int = 5
    min_score: float = 0.2  # floor of the eq. 9 score (range [-1, 1] for unit vectors)
    consistency: int = 3  # consecutive keyframes agreeing on a candidate group; as many verifications close a loop
    min_keyframes: int = 10  # no detection in a map smaller than this
    exclude_recent: int = 10  # never match one of the last keyframes (they are odometry, not loops)
    max_distance_binary: float = 64.0
    max_distance_float: float = 0.7
    ratio: float = 0.8
    min_matches: int = 20  # descriptor matches before Sim3 RANSAC
    pair_matcher_min_inliers: int = 6  # kNN matches agreeing on one Sim3 before the pair matcher is asked for more
    min_inliers: int = 20
    min_projected_matches: int = 40  # matches of the loop group's points after the guided search
    search_radius: float = 10.0
    covisibility_edge_weight: int = 100  # covisibility edges of the essential graph
    global_bundle_adjustment: bool = False  # after a loop; ~15 s for 67 keyframes, a stall in sync mode
    global_ba_iterations: tuple[int, int] = (5, 10)
    merge: bool = True  # merge the active map into an inactive one when a keyframe links them
    merge_recent: int = 3  # last keyframes of each inactive map tried for a merge (works without global descriptors)
    merge_top_k: int = 3  # best-scoring keyframes of the inactive maps tried (with a global descriptor)


class KeyFrameDatabase:
    """Global descriptors of the map's keyframes, scored all at once (eq. 9)."""

    def __init__(self):
        self.keyframes: list[KeyFrame] = []
        self.vectors: np.ndarray | None = None
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def add(self, kf: KeyFrame) -> None:
        alive = [i for i, k in enumerate(self.keyframes) if not k.is_bad]
        if len(alive) < self._n:  # culled keyframes leave (ORB-SLAM's KeyFrameDatabase::erase)
            self.keyframes = [self.keyframes[i] for i in alive]
            self.vectors[: len(alive)] = self.vectors[alive]
            self._n = len(alive)
        v = np.asarray(kf.global_descriptor, np.float64).ravel()
        v = v / max(float(np.linalg.norm(v)), 1e-12)
        if self.vectors is None:
            self.vectors = np.zeros((64, len(v)))  # float64: 1 - sqrt(2 - 2 a.b) is ill-conditioned near a = b
        if self._n == len(self.vectors):
            self.vectors = np.concatenate([self.vectors, np.zeros_like(self.vectors)])
        self.vectors[self._n] = v
        self.keyframes.append(kf)
        self._n += 1

    def scores(self, descriptor: np.ndarray) -> np.ndarray:
        """Eq. 9 for every stored keyframe: 1 - ||a - b|| with a, b unit vectors, via one matrix product."""
        if self._n == 0:
            return np.zeros(0, np.float32)
        q = np.asarray(descriptor, np.float64).ravel()
        q = q / max(float(np.linalg.norm(q)), 1e-12)
        dots = self.vectors[: self._n] @ q
        return 1.0 - np.sqrt(np.maximum(2.0 - 2.0 * dots, 0.0))

    def query(self, descriptor: np.ndarray, k: int, exclude=(), min_score: float = -np.inf,
              maps=None) -> list[KeyFrame]:
        """Top-k keyframes by score, above `min_score`, skipping culled and excluded ones (and, given `maps`,
        keyframes that live in none of them)."""
        s = self.scores(descriptor)
        out = []
        for i in np.argsort(-s, kind="stable"):
            kf = self.keyframes[i]
            if s[i] < min_score or len(out) == k:
                break
            if not kf.is_bad and kf not in exclude and (maps is None or _map_of(kf) in maps):
                out.append(kf)
        return out


def _map_of(kf: KeyFrame) -> Map | None:
    return kf.map.resolved() if kf.map is not None else None


class LoopCloser:
    def __init__(self, atlas: Atlas, mapper, cfg: LoopConfig, binary: bool, stereo: bool, seed: int = 0,
                 pair_matcher=None):
        self.atlas, self.mapper, self.cfg, self.binary, self.stereo = atlas, mapper, cfg, binary, stereo
        self.seed, self.pair_matcher = seed, pair_matcher  # pair_matcher: as the Tracker's, for verification
        self.max_distance = cfg.max_distance_binary if binary else cfg.max_distance_float
        self.database = KeyFrameDatabase()
        self.groups: list[tuple[set[KeyFrame], int]] = []
        self.last_loop_id = -(10**9)
        self.streak: tuple[set[KeyFrame], int] = (set(), 0)  # the last keyframe's verified loop group, and its run
        self.loops: list[tuple[int, int]] = []  # (frame index of the current keyframe, of the loop keyframe)
        self.merges: list[tuple[int, int]] = []  # (frame index of the active map's keyframe, of the other map's)

    @property
    def map(self) -> Map:
        return self.atlas.active

    def process(self, kf: KeyFrame) -> None:
        with self.atlas.lock:
            current = not kf.is_bad and _map_of(kf) is self.map
            if current and self.cfg.enabled and kf.global_descriptor is not None:
                verified = set()
                for cand in self._detect(kf):  # the best-scoring candidate that verifies (cost check or streak)
                    found = self._verify(kf, cand)
                    if found is not None:
                        if not self._undoes_the_motion(kf, cand, found[0]):
                            verified = {cand, *self.map.neighbours(cand)}
                            repeated = self._repeated(verified) and not self._turns_out_of_view(kf, cand, found[0])
                            if repeated or self._lowers_residuals(kf, cand, found[0], found[2]):
                                self._correct(kf, cand, *found[:2])
                                verified = set()
                        break
                self.streak = (verified, self.streak[1] + 1 if verified & self.streak[0] else int(bool(verified)))
            if current and self.cfg.merge and self.atlas.inactive():
                for cand in self._merge_candidates(kf):
                    found = self._verify(kf, cand)
                    if found is not None:
                        self._merge(kf, cand, *found[:2])
                        break
            if kf.global_descriptor is not None:
                self.database.add(kf)

    # --- map merging -------------------------------------------------------------------------------------------
    def _merge_candidates(self, kf: KeyFrame) -> list[KeyFrame]:
        c = self.cfg
        others = self.atlas.inactive()
        out = [k for m in others for k in m.keyframes[-c.merge_recent:][::-1]]
        if kf.global_descriptor is not None and len(self.database):
            out += self.database.query(kf.global_descriptor, c.merge_top_k, set(out), c.min_score, maps=others)
        return out

    def _merge(self, kf: KeyFrame, cand: KeyFrame, S12: np.ndarray, loop_points: np.ndarray) -> None:
        """Move the active map into cand's map (x_target = S x_active), then fuse and link the joined region."""
        target = _map_of(cand)
        S = inverse_pose(S12 @ cand.T_cw) @ kf.T_cw
        log.info("Maps merged: keyframe %d (frame %d) of map %d <-> keyframe %d (frame %d) of map %d, scale %.3f.",
                 kf.id, kf.index, self.map.id, cand.id, cand.index, target.id, np.cbrt(np.linalg.det(S[:3, :3])))
        self.atlas.merge(self.map, target, S)
        connected = [kf, *target.neighbours(kf)]
        for k in connected:
            self.mapper.fuse_points(k, loop_points)
        for k in connected:
            target.update_connections(k)
        kf.loop_edges.add(cand)
        cand.loop_edges.add(kf)
        self.merges.append((kf.index, cand.index))
        self.groups = []
        self.last_loop_id = kf.id

    # --- detection ---------------------------------------------------------------------------------------------
    def _detect(self, kf: KeyFrame) -> list[KeyFrame]:
        c = self.cfg
        if len(self.map.keyframes) < c.min_keyframes or kf.id - self.last_loop_id < c.exclude_recent:
            self.groups = []
            return []
        neighbours = self.map.neighbours(kf)
        scores = self.database.scores(kf.global_descriptor)
        position = {k: i for i, k in enumerate(self.database.keyframes)}
        neighbour_scores = [scores[position[n]] for n in neighbours if n in position]
        threshold = max(c.min_score, min(neighbour_scores)) if neighbour_scores else c.min_score
        recent = {k for k in self.database.keyframes if k.id > kf.id - c.exclude_recent}
        candidates = self.database.query(kf.global_descriptor, c.top_k, {kf, *neighbours, *recent}, threshold,
                                         maps=[self.map])
        enough, groups = [], []
        for cand in candidates:
            group = {cand, *self.map.neighbours(cand)}
            counts = [n + 1 for g, n in self.groups if g & group]
            count = max(counts) if counts else 0
            groups.append((group, count))
            if count >= c.consistency - 1 and cand not in enough:
                enough.append(cand)
        self.groups = groups
        log.debug("Loop query for %s: threshold %.3f, candidates %s, consistent %s.", kf, threshold,
                  [(k.index, round(float(scores[position[k]]), 3)) for k in candidates], [k.index for k in enough])
        return enough

    # --- verification ------------------------------------------------------------------------------------------
    def _verify(self, kf: KeyFrame, cand: KeyFrame):
        c = self.cfg
        s = self.atlas.store
        ia, ib = s.matched(kf), s.matched(cand)
        if len(ia) < c.min_matches or len(ib) < c.min_matches:
            return None
        a, b = match_knn_ratio(kf.descriptors[ia], cand.descriptors[ib], self.binary, self.max_distance, c.ratio)
        a, b = ia[a], ib[b]
        if (len(a) < c.min_matches and self.pair_matcher is not None
                and self._similarity(kf, cand, a, b, c.pair_matcher_min_inliers) is not None):
            # the learned matcher when kNN finds too few, but enough of them agree on one similarity (a look-alike
            # place's few kNN matches agree on none, and LighterGlue costs 0.3-1 s): all keypoints matched, then
            # those with map points on both sides kept
            a, b = self.pair_matcher(kf.keypoints, kf.descriptors, kf.image_size, cand.keypoints, cand.descriptors,
                                     cand.image_size)
            keep = np.isin(a, ia) & np.isin(b, ib)
            a, b = a[keep], b[keep]
        if len(a) < c.min_matches:
            log.debug("Candidate %s for %s rejected: %d descriptor matches.", cand, kf, len(a))
            return None
        out = self._similarity(kf, cand, a, b, c.min_inliers)
        if out is None:
            log.debug("Candidate %s for %s rejected: no Sim3 with %d inliers.", cand, kf, c.min_inliers)
            return None
        S12, _ = out
        loop_kfs = [cand, *_map_of(cand).neighbours(cand, 10)]
        loop_points = s.seen_by(loop_kfs)
        X = s.position[loop_points]
        Xc = transform(S12 @ cand.T_cw, X)
        z = Xc[:, 2]
        uv = Xc[:, :2] / np.where(z > 1e-9, z, 1e-9)[:, None] @ kf.K[:2, :2].T + kf.K[:2, 2]
        vis = np.nonzero((z > 0) & kf.in_image(uv))[0]
        ip, ik = match_in_windows(uv[vis], s.descriptor[loop_points[vis]], kf.keypoints, kf.descriptors,
                                  c.search_radius, self.binary, self.max_distance, ratio=0.9)
        if len(ip) < c.min_projected_matches:
            log.debug("Loop candidate %s for %s rejected: %d projected matches.", cand, kf, len(ip))
            return None
        return S12, loop_points, (loop_points[vis[ip]], ik)

    def _similarity(self, kf: KeyFrame, cand: KeyFrame, a: np.ndarray, b: np.ndarray, min_inliers: int):
        """Sim3 RANSAC (SE3 in stereo) on the map points of keypoints kf[a] <-> cand[b]: (S12, inliers) or None."""
        s = self.atlas.store
        P1 = transform(kf.T_cw, s.position[kf.points[a]])
        P2 = transform(cand.T_cw, s.position[cand.points[b]])
        return sim3_ransac(P1, P2, kf.keypoints[a], cand.keypoints[b], kf.K, cand.K, with_scale=not self.stereo,
                           seed=self.seed + kf.id, min_inliers=min_inliers)

    # --- correction --------------------------------------------------------------------------------------------
    def _correct(self, kf: KeyFrame, cand: KeyFrame, S12: np.ndarray, loop_points: np.ndarray) -> None:
        log.info("Loop closed: keyframe %d (frame %d) <-> keyframe %d (frame %d).", kf.id, kf.index, cand.id,
                 cand.index)
        self.map.update_connections(kf)
        connected = [kf, *self.map.neighbours(kf)]
        before = {k: k.T_cw.copy() for k in connected}
        corrected = self._propagated(kf, cand, S12)
        s = self.atlas.store
        corrected_by: dict[int, KeyFrame] = {}  # point id -> the keyframe whose correction moved it
        for k in connected:
            move = inverse_pose(corrected[k]) @ before[k]
            for j in s.alive(k.points).tolist():
                if j not in corrected_by:
                    s.position[j] = transform(move, s.position[j][None])[0]
                    corrected_by[j] = k
            k.T_cw = _rigid(corrected[k])
            k.scale /= _scale(corrected[k])
        # the loop's links are the neighbours fusing adds across the loop; one it adds to a keyframe the group already
        # neighboured (this side of the loop) would pin the correction's step between the group and its own track
        this_side = set(connected).union(*(self.map.neighbours(k) for k in connected))
        for k in connected:
            self.mapper.fuse_points(k, loop_points, replace_with_new=True)
        new_links = {}
        for k in connected:
            self.map.update_connections(k)
            new_links[k] = set(self.map.neighbours(k)) - this_side
        kf.loop_edges.add(cand)
        cand.loop_edges.add(kf)
        self._optimize_essential_graph(kf, cand, before, corrected, corrected_by, new_links)
        update_normals(s, self.map.points, force=True)
        if self.cfg.global_bundle_adjustment:
            kfs = [k for k in self.map.keyframes if not k.is_bad]
            fixed = np.zeros(len(kfs), bool)
            fixed[0] = True
            self.mapper.bundle_adjust(kfs, fixed, self.map.sorted_points(),
                                      self.cfg.global_ba_iterations)
        self.last_loop_id = kf.id
        self.loops.append((kf.index, cand.index))
        self.groups = []

    def _propagated(self, kf: KeyFrame, cand: KeyFrame, S12: np.ndarray) -> dict[KeyFrame, np.ndarray]:
        """The loop's similarity S_kw for kf, carried to its covisible neighbours by their relative poses."""
        S_kw = S12 @ cand.T_cw
        return {k: k.T_cw @ inverse_pose(kf.T_cw) @ S_kw for k in [kf, *self.map.neighbours(kf)]}

    def _repeated(self, group: set[KeyFrame]) -> bool:
        """Whether the keyframes just before verified a loop to this place too, `consistency` in a row with this one
        (ORB-SLAM3 closes a loop verified by three consecutive keyframes): a false loop to a look-alike place rarely
        verifies twice in a row, and a true one after a large drift can fail the cost prediction."""
        last, run = self.streak
        if group & last and run + 1 >= self.cfg.consistency:
            log.info("Loop verified by %d keyframes in a row: closed without the cost check.", run + 1)
            return True
        return False

    def _turns_out_of_view(self, kf: KeyFrame, cand: KeyFrame, S12: np.ndarray) -> bool:
        if turns_out_of_view(kf.T_cw, S12 @ cand.T_cw, kf.K, kf.image_size):
            log.info("Loop %s <-> %s not closed without the cost check: its correction turns the camera by more "
                     "than half its field of view.", kf, cand)
            return True
        return False

    def _undoes_the_motion(self, kf: KeyFrame, cand: KeyFrame, S12: np.ndarray) -> bool:
        path = sorted((k for k in self.map.keyframes if not k.is_bad and cand.index <= k.index <= kf.index),
                      key=lambda k: k.index)
        if undoes_the_motion(np.stack([k.T_cw for k in path]), S12 @ cand.T_cw):
            log.info("Loop %s <-> %s refused: its correction undoes most of the motion between them.", kf, cand)
            return True
        return False

    def _lowers_residuals(self, kf: KeyFrame, cand: KeyFrame, S12: np.ndarray,
                          matches: tuple[np.ndarray, np.ndarray]) -> bool:
        """Whether the correction lowers the robust reprojection cost of the map's observations plus the loop's
        matches, predicted before anything changes: the essential graph solved on the current graph (the loop's
        keyframes linked as fusing their points would link them), every point moved with its reference keyframe,
        then the points re-estimated for each side's poses (`_structure_cost`). A true loop pays for its drift with
        small strains along the graph; a false one (repetitive texture, a look-alike place) bends the map and raises
        the cost."""
        corrected = self._propagated(kf, cand, S12)
        loop_group = {cand, *self.map.neighbours(cand, 10)} - set(corrected)  # linked once the points are fused
        links = {k: loop_group for k in corrected}
        kfs, idx, _, odometry, out = self._essential_graph(kf, cand, corrected, {}, links)
        s = self.atlas.store
        pose, key, point = [], [], []
        for k in kfs:
            has = np.nonzero(k.points >= 0)[0]
            has = has[~s.bad[k.points[has]]]
            pose.append(np.full(len(has), idx[k]))
            key.append(k.keypoints[has])
            point.append(k.points[has])
        loop_ids, loop_keys = matches
        pose = np.concatenate([*pose, np.full(len(loop_ids), idx[kf])])
        uv = np.concatenate([*key, kf.keypoints[loop_keys]])
        point = np.concatenate([*point, loop_ids])
        ids, inverse = np.unique(point, return_inverse=True)
        refs = np.array([idx.get(s.reference[j], -1) for j in ids])
        for a, j in enumerate(ids):  # a point whose reference left the map moves with an observer in it
            if refs[a] < 0:
                refs[a] = next((idx[k] for k in s.observations[j] if k in idx), idx[cand])
        before_poses = np.stack(odometry)
        move = np.einsum("nij,njk->nik", np.stack([inverse_pose(S) for S in out])[refs], before_poses[refs])
        X = s.position[ids]
        X_after = np.einsum("nij,nj->ni", move[:, :3, :3], X) + move[:, :3, 3]
        order = np.argsort(pose, kind="stable")  # the BA's observation layout: sorted by pose
        obs = (pose[order], inverse[order], uv[order], np.zeros(len(pose), bool))
        cost_before = self._structure_cost(before_poses, X, obs, kf.K)
        cost_after = self._structure_cost(out, X_after, obs, kf.K)
        if cost_after >= cost_before:
            log.info("Loop %s <-> %s refused: the correction raises the reprojection cost (%.0f -> %.0f).", kf,
                     cand, cost_before, cost_after)
        return cost_after < cost_before

    def _structure_cost(self, poses: np.ndarray, X: np.ndarray, obs, K: np.ndarray) -> float:
        """The robust reprojection cost once the points are re-estimated for these poses (held): a correction is
        judged by the structure it allows; points dragged rigidly with their reference keyframes would charge a large
        drift's correction (a lap's 4x scale on the tiled pool) for strain the structure absorbs."""
        _, X, _ = bundle_adjustment(poses, np.ones(len(poses), bool), X, obs[0], obs[1], obs[2], K,
                                    iterations=(STRUCTURE_ITERATIONS,), sigma=self.mapper.sigma, solver="schur")
        return robust_cost(poses, X, obs, np.ones(len(obs[0]), bool), K, sigma=self.mapper.sigma)

    def _optimize_essential_graph(self, kf, cand, before, corrected, corrected_by, new_links) -> None:
        kfs, idx, initial, odometry, out = self._essential_graph(kf, cand, corrected, before, new_links)
        s = self.atlas.store
        for j in self.map.points:
            ref = corrected_by.get(j, s.reference[j])
            if ref not in idx:
                ref = next((k for k in s.observations[j] if k in idx), None)
                if ref is None:
                    continue
            i = idx[ref]
            frame_of_point = initial[i] if j in corrected_by else odometry[i]  # the pose the point agrees with
            s.position[j] = transform(inverse_pose(out[i]) @ frame_of_point, s.position[j][None])[0]
        for k, S, S0 in zip(kfs, out, initial, strict=True):
            k.T_cw = _rigid(S)
            k.scale *= _scale(S0) / _scale(S)

    def _essential_graph(self, kf, cand, corrected, before, new_links):
        """The essential graph (spanning tree, loop edges, strong covisibility, the new loop links) solved from the
        corrected poses: (keyframes, their index, initial poses, pre-loop poses, optimised similarities S_iw)."""
        kfs = [k for k in self.map.keyframes if not k.is_bad]
        idx = {k: i for i, k in enumerate(kfs)}
        initial = np.stack([corrected.get(k, k.T_cw) for k in kfs])  # corrected similarities, or current poses
        odometry = [before.get(k, k.T_cw) for k in kfs]  # relative measurements keep the pre-loop odometry
        edges, rel, seen = [], [], set()

        def add(a: KeyFrame, b: KeyFrame, poses) -> None:
            if a in idx and b in idx and a is not b and (b, a) not in seen and (a, b) not in seen:
                seen.add((a, b))
                edges.append((idx[a], idx[b]))
                rel.append(poses[idx[a]] @ inverse_pose(poses[idx[b]]))

        for k, links in new_links.items():
            for n in links:
                add(k, n, initial)
        add(kf, cand, initial)
        for k in kfs:
            if k.parent is not None:
                add(k, k.parent, odometry)
            for m in k.loop_edges:
                add(k, m, initial)
            for n, w in self.map.covisibility.get(k, {}).items():
                if w >= self.cfg.covisibility_edge_weight and n.id < k.id:
                    add(k, n, odometry)
        out = pose_graph_optimization(initial, np.array(edges), np.stack(rel), [idx[cand]],
                                      similarity=not self.stereo)
        return kfs, idx, initial, odometry, out


def undoes_the_motion(path: np.ndarray, S_kw: np.ndarray) -> bool:
    """Whether a loop's corrected pose S_kw of the last keyframe of `path` (rigid T_cw [n, 4, 4], from the loop's
    candidate to that keyframe) undoes more than half of the motion along the path, of the rotation turned and of the
    distance travelled alike. Drift is a fraction of the motion; a correction that large takes a look-alike place (the
    next corner of a tiled floor, a whole number of tiles away) for this one."""
    R, centres = path[:, :3, :3], np.array([inverse_pose(T)[:3, 3] for T in path])
    travelled = np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()
    turned = sum(rotation_deg(a @ b.T) for a, b in zip(R[1:], R[:-1], strict=True))
    shift = np.linalg.norm(inverse_pose(S_kw)[:3, 3] - centres[-1])
    return bool(shift > 0.5 * travelled and rotation_deg(S_kw[:3, :3] / _scale(S_kw) @ R[-1].T) > 0.5 * turned)


def turns_out_of_view(T_cw: np.ndarray, S_kw: np.ndarray, K: np.ndarray, image_size: tuple[int, int]) -> bool:
    """Whether a loop's corrected pose S_kw turns the camera at T_cw by more than half its horizontal field of view.
    Tracking keeps consecutive views overlapping, so its heading drift stays well inside that; a look-alike place on
    a symmetric pattern (a tiled floor seen after a 90 or 180 deg turn) asks for the whole turn."""
    half_fov = np.degrees(np.arctan(0.5 * image_size[0] / K[0, 0]))
    return rotation_deg(S_kw[:3, :3] / _scale(S_kw) @ T_cw[:3, :3].T) > half_fov


def _scale(S: np.ndarray) -> float:
    return float(np.cbrt(np.linalg.det(S[:3, :3])))


def _rigid(S: np.ndarray) -> np.ndarray:
    """[sR | t] -> [R | t/s]: the camera pose in the scale of the corrected map."""
    s = _scale(S)
    return pose_matrix(S[:3, :3] / s, S[:3, 3] / s)
