"""Plain map types: Frame, KeyFrame, the PointStore of map points and the Map with its covisibility graph
(ORB-SLAM's vocabulary).

Poses are stored as ``T_cw`` (world -> camera 0), keypoints are undistorted pixel coordinates of the ideal pinhole
``K`` of camera 0. A stereo frame also carries, per keypoint, the matched undistorted right-image coordinate and the
stereo depth (NaN where the keypoint has no stereo match). The Map owns one re-entrant lock that the threaded mode
takes around every mapping step; the synchronous mode never contends for it.

Map points are rows of arrays (`PointStore`), named by their row: a frame's points are an index array, and the
thousands of positions or descriptors a step needs are one slice, not a stack of per-point objects.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np


def inverse_pose(T: np.ndarray) -> np.ndarray:
    """Exact inverse of a 4x4 rigid transform or similarity [sR | t]."""
    A_inv = np.linalg.inv(T[:3, :3])
    out = np.eye(4)
    out[:3, :3] = A_inv
    out[:3, 3] = -A_inv @ T[:3, 3]
    return out


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation of a rigid transform back onto SO(3) (products of many poses drift off it)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def transform(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points [N, 3]."""
    return X @ T[:3, :3].T + T[:3, 3]


def scale_translation(T: np.ndarray, ratio: float) -> np.ndarray:
    """A relative rigid pose re-expressed in a map whose scale changed by `ratio` (translation scales)."""
    if ratio == 1.0:
        return T
    out = T.copy()
    out[:3, 3] *= ratio
    return out


@dataclass(eq=False)
class Frame:
    index: int
    timestamp: float
    keypoints: np.ndarray  # [N, 2] undistorted pixels (camera 0)
    descriptors: np.ndarray  # [N, D] float32 or uint8 packed bits
    K: np.ndarray  # 3x3 ideal pinhole of camera 0
    image_size: tuple[int, int]  # (width, height)
    global_descriptor: np.ndarray | None = None
    scales: np.ndarray | None = None  # [N] pyramid scale of each keypoint's detection, None = all full size
    right: np.ndarray | None = None  # [N, 2] undistorted right pixels, NaN where no stereo match
    depth: np.ndarray | None = None  # [N] stereo depth in camera 0, NaN where none
    T_cw: np.ndarray | None = None
    points: np.ndarray | None = None  # [N] map point ids (rows of the run's `PointStore`), -1 = none
    outliers: np.ndarray | None = None  # [N] bool, set by pose optimisation

    def __post_init__(self):
        n = len(self.keypoints)
        if self.points is None:
            self.points = np.full(n, -1, np.int64)
        if self.outliers is None:
            self.outliers = np.zeros(n, bool)

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def center(self) -> np.ndarray:
        R, t = self.T_cw[:3, :3], self.T_cw[:3, 3]
        return -(R.T @ t)

    def clear_points(self) -> None:
        self.points = np.full(len(self), -1, np.int64)

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [M, 3] -> (pixels [M, 2], depths [M])."""
        Xc = transform(self.T_cw, X)
        z = Xc[:, 2]
        uv = Xc[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None] * self.K[[0, 1], [0, 1]] + self.K[:2, 2]
        return uv, z

    def in_image(self, uv: np.ndarray, border: float = 0.0) -> np.ndarray:
        w, h = self.image_size
        return (uv[:, 0] >= border) & (uv[:, 1] >= border) & (uv[:, 0] < w - border) & (uv[:, 1] < h - border)


class KeyFrame(Frame):
    """A frame kept in the map; `id` is unique in its run and increasing in insertion order (`Map.new_keyframe`)."""

    def __init__(self, frame: Frame, id: int):
        super().__init__(
            index=frame.index, timestamp=frame.timestamp, keypoints=frame.keypoints,
            descriptors=frame.descriptors, K=frame.K, image_size=frame.image_size,
            global_descriptor=frame.global_descriptor, scales=frame.scales, right=frame.right, depth=frame.depth,
            T_cw=frame.T_cw.copy(), points=frame.points.copy(),
        )
        self.id = id
        self.is_bad = False
        self.parent: KeyFrame | None = None  # spanning tree, for the essential graph and culled keyframes
        self.T_parent: np.ndarray | None = None  # T_cw relative to the parent, kept when culled
        self.loop_edges: set[KeyFrame] = set()
        self.map: Map | None = None  # the map it was added to (follow `Map.resolved()` after merges)
        # Monocular maps change scale (loop Sim3, map merge): relative poses kept against this keyframe (frames of
        # the trajectory, the tracker's last frame, a culled child) are rescaled by the change of `scale`.
        self.scale = 1.0
        self.T_parent_scale = 1.0  # the parent's scale when T_parent was taken

    def __hash__(self) -> int:
        return self.id

    def __repr__(self) -> str:
        return f"KeyFrame(id={self.id}, frame={self.index})"

    def pose(self) -> np.ndarray:
        """T_cw, also for a culled keyframe (through its parent chain)."""
        if not self.is_bad:
            return self.T_cw
        return scale_translation(self.T_parent, self.parent.current_scale() / self.T_parent_scale) @ self.parent.pose()

    def current_scale(self) -> float:
        """`scale`, also for a culled keyframe (its frozen scale carried forward by its parent's later changes)."""
        if not self.is_bad:
            return self.scale
        return self.scale * self.parent.current_scale() / self.T_parent_scale

    def release(self) -> None:
        """A culled keyframe keeps only its place in the spanning tree (the trajectory records point at it): its
        keypoints, descriptors and global descriptor are dropped, or a long run grows by every keyframe culled."""
        # copies: an empty slice is a view that would keep the whole array alive
        self.keypoints, self.descriptors = self.keypoints[:0].copy(), self.descriptors[:0].copy()
        self.points, self.outliers = self.points[:0].copy(), self.outliers[:0].copy()
        self.global_descriptor = self.right = self.depth = None


class PointStore:
    """Every map point of one run as a row of arrays (its id), shared by the maps of the run's Atlas.

    Frames hold point ids (`Frame.points`, -1 = none); the steps that need many points at once (projection,
    matching, bundle adjustment) slice these arrays instead of stacking per-point objects. Ids count from 0 in
    every run: they order sets and seed nothing that depends on an earlier run in the same process. A row is never
    reused: a culled point keeps it with `bad` set, a fused-away one also points to its survivor (`replaced_by`).
    """

    def __init__(self, capacity: int = 1024):
        self.size = 0
        self.position = np.zeros((capacity, 3))
        self.normal = np.zeros((capacity, 3))
        self.descriptor: np.ndarray | None = None  # [capacity, D], the extractor's dtype (set by the first point)
        self.visible = np.zeros(capacity, np.int64)  # frames in whose frustum it fell
        self.found = np.zeros(capacity, np.int64)  # frames where it was matched
        self.bad = np.zeros(capacity, bool)
        self.first_kf_id = np.zeros(capacity, np.int64)
        self.replaced_by = np.full(capacity, -1, np.int64)
        self.observations: list[dict[KeyFrame, int]] = []  # per point: observing keyframe -> keypoint index
        self.reference: list[KeyFrame] = []  # the keyframe that created it (for loop correction)
        self.normal_key: list = []  # what the cached normal / descriptor were computed from
        self.descriptor_key: list = []

    def add(self, position: np.ndarray, descriptor: np.ndarray, reference: KeyFrame) -> int:
        j = self.size
        if self.descriptor is None:
            self.descriptor = np.zeros((len(self.position), len(descriptor)), descriptor.dtype)
        if j == len(self.position):
            self._grow()
        self.position[j] = position
        self.normal[j] = 0.0
        self.descriptor[j] = descriptor
        self.visible[j] = self.found[j] = 1
        self.first_kf_id[j] = reference.id
        self.observations.append({})
        self.reference.append(reference)
        self.normal_key.append(None)
        self.descriptor_key.append(None)
        self.size += 1
        return j

    def _grow(self) -> None:
        for name in ("position", "normal", "descriptor", "visible", "found", "bad", "first_kf_id", "replaced_by"):
            a = getattr(self, name)
            grown = np.full((2 * len(a), *a.shape[1:]), -1 if name == "replaced_by" else 0, a.dtype)
            grown[: len(a)] = a
            setattr(self, name, grown)

    def add_observation(self, j: int, kf: KeyFrame, index: int) -> None:
        self.observations[j][kf] = index
        kf.points[index] = j

    def retire(self, j: int) -> None:
        """A removed or merged point: marked bad, its observations and cache keys dropped (its row stays)."""
        self.bad[j] = True
        self.observations[j] = {}
        self.normal_key[j] = self.descriptor_key[j] = None

    def alive(self, ids: np.ndarray) -> np.ndarray:
        """The ids that name a live point (not -1, not culled or fused away), in their order."""
        ids = ids[ids >= 0]
        return ids[~self.bad[ids]]

    def seen_by(self, frames) -> np.ndarray:
        """The live points any of `frames` holds, each once, in id order (local map, BA, fusion and loop sets)."""
        return self.alive(np.unique(np.concatenate([f.points for f in frames])))

    def matched(self, frame: Frame) -> np.ndarray:
        """Keypoint indices of `frame` with a live point."""
        ids = frame.points
        ok = ids >= 0
        ok[ok] = ~self.bad[ids[ok]]
        return np.nonzero(ok)[0]

    def resolve(self, ids: np.ndarray) -> np.ndarray:
        """Each id followed through fusions to its surviving point; -1 for a culled one."""
        out = ids.copy()
        while True:
            stale = out >= 0
            stale[stale] = self.bad[out[stale]]
            if not stale.any():
                return out
            out[stale] = self.replaced_by[out[stale]]

    def num_observations(self, ids) -> np.ndarray:
        return np.array([len(self.observations[j]) for j in ids], np.int64)

    def set_normals(self, ids: np.ndarray, normals: np.ndarray) -> None:
        """Normals computed elsewhere (all new points of a triangulation at once) for the current observers."""
        self.normal[ids] = normals
        for j in ids:
            self.normal_key[j] = tuple(kf.id for kf in self.observations[j])


def update_normals(store: PointStore, ids, force: bool = False) -> None:
    """Each point's mean viewing direction over its observing keyframes (for the viewing-angle test of the search).

    Recomputed where the observing keyframes changed (or `force`, after a loop correction moved the points); the
    small moves of a local BA do not matter to a 60-degree viewing-angle test. Points with the same number of
    observers are done in one batch.
    """
    stale: dict[int, list[int]] = {}
    for j in ids:
        key = tuple(kf.id for kf in store.observations[j])
        if key and (force or key != store.normal_key[j]):
            store.normal_key[j] = key
            stale.setdefault(len(key), []).append(j)
    observers = {kf for group in stale.values() for j in group for kf in store.observations[j]}
    centres = {kf: kf.center for kf in observers}
    for group in stale.values():
        C = np.array([centres[kf] for j in group for kf in store.observations[j]]).reshape(len(group), -1, 3)
        d = store.position[group][:, None] - C
        d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
        n = d.sum(1)
        n /= np.maximum(np.sqrt((n * n).sum(1)), 1e-12)[:, None]
        store.normal[group] = n


def update_descriptors(store: PointStore, ids, binary: bool) -> None:
    """Each point's descriptor: the observation descriptor with the least median distance to the others (ORB-SLAM's
    choice), recomputed only where the observations changed. Points with the same number of observations are done
    in one batch (a keyframe's few thousand points: ~50 batched products instead of one small product per point).
    """
    stale: dict[int, list[int]] = {}
    for j in ids:
        key = tuple((kf.id, i) for kf, i in store.observations[j].items())
        if key != store.descriptor_key[j] and key:
            store.descriptor_key[j] = key
            stale.setdefault(len(key), []).append(j)
    for n, group in stale.items():
        descs = np.array([kf.descriptors[i] for j in group for kf, i in store.observations[j].items()])
        descs = descs.reshape(len(group), n, -1)  # [points, observations, descriptor]
        if n < 3:
            best = np.full(len(group), n - 1)
        else:
            d = np.sort(_batched_distances(descs, binary), axis=2)
            best = np.argmin(d[:, :, (n - 1) // 2], axis=1)  # lower median, as ORB-SLAM
        store.descriptor[group] = descs[np.arange(len(group)), best]


def _batched_distances(descs: np.ndarray, binary: bool) -> np.ndarray:
    """`descriptor_distances(a, a)` for each [n, D] set of a batch [B, n, D] -> [B, n, n] (float32)."""
    if binary:
        return np.bitwise_count(descs[:, :, None] ^ descs[:, None]).sum(-1, dtype=np.int32).astype(np.float32)
    a = descs.astype(np.float32, copy=False)
    sq = (a * a).sum(2)
    d2 = sq[:, :, None] + sq[:, None] - 2.0 * a @ a.transpose(0, 2, 1)
    return np.sqrt(np.maximum(d2, 0.0))


class Map:
    """One connected map: its keyframes, the ids of its points (rows of the run's `PointStore`, shared by the maps of
    an Atlas with its lock and keyframe numbering) and the covisibility graph."""

    def __init__(self, lock: threading.RLock | None = None, id: int = 0, store: PointStore | None = None,
                 keyframe_ids: Iterator[int] | None = None):
        self.id = id
        self.store = store if store is not None else PointStore()
        self.keyframe_ids = keyframe_ids if keyframe_ids is not None else itertools.count()  # from 0 in every run
        self.keyframes: list[KeyFrame] = []  # insertion order, culled ones removed
        self.points: set[int] = set()
        self.covisibility: dict[KeyFrame, dict[KeyFrame, int]] = {}
        self.lock = lock or threading.RLock()
        self.merged_into: Map | None = None

    def resolved(self) -> Map:
        """The map this one lives on in (itself, or the map it was merged into)."""
        m = self
        while m.merged_into is not None:
            m = m.merged_into
        return m

    def __repr__(self) -> str:
        return f"Map(id={self.id}, keyframes={len(self.keyframes)})"

    def sorted_points(self) -> np.ndarray:
        return np.array(sorted(self.points), np.int64)

    # --- keyframes -------------------------------------------------------------------------------------------
    def new_keyframe(self, frame: Frame) -> KeyFrame:
        kf = KeyFrame(frame, next(self.keyframe_ids))
        self.add_keyframe(kf)
        return kf

    def add_keyframe(self, kf: KeyFrame) -> None:
        self.keyframes.append(kf)
        self.covisibility[kf] = {}
        kf.map = self

    def update_connections(self, kf: KeyFrame, min_weight: int = 15) -> None:
        """Covisibility weights = number of shared map points; spanning-tree parent = strongest older neighbour."""
        counts: dict[KeyFrame, int] = {}
        for j in self.store.alive(kf.points):
            for other in self.store.observations[j]:
                if other is not kf and not other.is_bad:
                    counts[other] = counts.get(other, 0) + 1
        if not counts:
            return
        strongest = max(counts, key=counts.get)
        kept = {o: w for o, w in counts.items() if w >= min_weight} or {strongest: counts[strongest]}
        old = self.covisibility.get(kf, {})
        for o in set(old) - set(kept):
            self.covisibility.get(o, {}).pop(kf, None)
        self.covisibility[kf] = kept
        for o, w in kept.items():
            self.covisibility.setdefault(o, {})[kf] = w
        if kf.parent is None and kf is not self.keyframes[0]:
            older = [o for o in counts if o.id < kf.id]
            if older:
                kf.parent = max(older, key=counts.get)

    def neighbours(self, kf: KeyFrame, n: int | None = None, min_weight: int = 0) -> list[KeyFrame]:
        """Covisible keyframes sorted by decreasing weight."""
        items = sorted(self.covisibility.get(kf, {}).items(), key=lambda kv: (-kv[1], kv[0].id))
        out = [o for o, w in items if w >= min_weight and not o.is_bad]
        return out if n is None else out[:n]

    def children(self, kf: KeyFrame) -> list[KeyFrame]:
        return [k for k in self.keyframes if k.parent is kf]

    def remove_keyframe(self, kf: KeyFrame) -> None:
        """Cull: drop its observations, re-parent its children, remember its pose relative to its parent."""
        if kf.parent is None:
            return  # the first keyframe anchors the map
        for j in kf.points[kf.points >= 0]:
            observations = self.store.observations[j]
            observations.pop(kf, None)
            if len(observations) < 2 and not self.store.bad[j]:
                self.remove_point(j)
        kf.points[:] = -1
        for child in self.children(kf):
            child.parent = kf.parent
        kf.T_parent = kf.T_cw @ inverse_pose(kf.parent.T_cw)
        kf.T_parent_scale = kf.parent.current_scale()
        for o in self.covisibility.pop(kf, {}):
            self.covisibility.get(o, {}).pop(kf, None)
        kf.is_bad = True
        self.keyframes.remove(kf)
        kf.release()

    # --- points ----------------------------------------------------------------------------------------------
    def new_point(self, position: np.ndarray, descriptor: np.ndarray, reference: KeyFrame) -> int:
        j = self.store.add(position, descriptor, reference)
        self.points.add(j)
        return j

    def remove_point(self, j: int) -> None:
        for kf, i in self.store.observations[j].items():
            if kf.points[i] == j:
                kf.points[i] = -1
        self.store.retire(j)
        self.points.discard(j)

    def replace_point(self, old: int, new: int) -> None:
        """Merge a duplicate: `new` inherits every observation of `old` (fusion and loop correction)."""
        if old == new:
            return
        s = self.store
        new_obs = s.observations[new]
        for kf, i in list(s.observations[old].items()):
            if kf in new_obs:
                kf.points[i] = -1
            else:
                s.add_observation(new, kf, i)
        s.visible[new] += s.visible[old]
        s.found[new] += s.found[old]
        s.retire(old)
        s.replaced_by[old] = new
        self.points.discard(old)
