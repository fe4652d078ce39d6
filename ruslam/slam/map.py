"""Plain map types: Frame, KeyFrame, MapPoint and the Map with its covisibility graph (ORB-SLAM's vocabulary).

Poses are stored as ``T_cw`` (world -> camera 0), keypoints are undistorted pixel coordinates of the ideal pinhole
``K`` of camera 0. A stereo frame also carries, per keypoint, the matched undistorted right-image coordinate and the
stereo depth (NaN where the keypoint has no stereo match). The Map owns one re-entrant lock that the threaded mode
takes around every mapping step; the synchronous mode never contends for it.

Rows of many objects (positions, descriptors) are gathered with `np.array(list)`: 2.4x faster than `np.stack` on
the thousands of rows a frame gathers.
"""

from __future__ import annotations

import itertools
import threading
from dataclasses import dataclass, field

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
    right: np.ndarray | None = None  # [N, 2] undistorted right pixels, NaN where no stereo match
    depth: np.ndarray | None = None  # [N] stereo depth in camera 0, NaN where none
    T_cw: np.ndarray | None = None
    points: list = field(default_factory=list)  # [N] MapPoint | None
    outliers: np.ndarray | None = None  # [N] bool, set by pose optimisation

    def __post_init__(self):
        n = len(self.keypoints)
        if not self.points:
            self.points = [None] * n
        if self.outliers is None:
            self.outliers = np.zeros(n, bool)

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def center(self) -> np.ndarray:
        R, t = self.T_cw[:3, :3], self.T_cw[:3, 3]
        return -(R.T @ t)

    def alive_points(self) -> list:
        """Its map points, without the culled and fused-away ones."""
        return [p for p in self.points if p is not None and not p.is_bad]

    def matched_indices(self) -> np.ndarray:
        return np.array([i for i, p in enumerate(self.points) if p is not None and not p.is_bad], dtype=int)

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [M, 3] -> (pixels [M, 2], depths [M])."""
        Xc = transform(self.T_cw, X)
        z = Xc[:, 2]
        uv = Xc[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None] * self.K[[0, 1], [0, 1]] + self.K[:2, 2]
        return uv, z

    def in_image(self, uv: np.ndarray, border: float = 0.0) -> np.ndarray:
        w, h = self.image_size
        return (uv[:, 0] >= border) & (uv[:, 1] >= border) & (uv[:, 0] < w - border) & (uv[:, 1] < h - border)


@dataclass
class Numbering:
    """The ids of one run's keyframes and points, shared by all the maps of its Atlas, from 0 in every run.

    Ids seed loop closing's RANSAC and order sets of keyframes and points; counters shared by the whole process
    made a run's result depend on what had run before it in the same process (a grid cell alone or after another).
    """

    keyframes: itertools.count = field(default_factory=itertools.count)
    points: itertools.count = field(default_factory=itertools.count)


class KeyFrame(Frame):
    """A frame kept in the map; `id` is unique in its run and increasing in insertion order (`Map.new_keyframe`)."""

    def __init__(self, frame: Frame, id: int):
        super().__init__(
            index=frame.index, timestamp=frame.timestamp, keypoints=frame.keypoints,
            descriptors=frame.descriptors, K=frame.K, image_size=frame.image_size,
            global_descriptor=frame.global_descriptor, right=frame.right, depth=frame.depth,
            T_cw=frame.T_cw.copy(), points=list(frame.points),
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


class MapPoint:
    def __init__(self, position: np.ndarray, descriptor: np.ndarray, reference: KeyFrame, id: int):
        self.id = id
        self.position = np.asarray(position, dtype=np.float64)
        self.descriptor = descriptor
        self.reference = reference  # keyframe that created it (for loop correction)
        self.observations: dict[KeyFrame, int] = {}
        self.normal = np.zeros(3)
        self.is_bad = False
        self.visible = 1  # frames in whose frustum it fell
        self.found = 1  # frames where it was matched
        self.first_kf_id = reference.id
        self.replaced_by: MapPoint | None = None
        self._normal_key = self._descriptor_key = None  # what the cached normal/descriptor were computed from

    def __hash__(self) -> int:
        return self.id

    def add_observation(self, kf: KeyFrame, index: int) -> None:
        self.observations[kf] = index
        kf.points[index] = self

    def set_normal(self, normal: np.ndarray) -> None:
        """A normal computed elsewhere (all new points of a triangulation at once) for the current observers."""
        self.normal = normal
        self._normal_key = tuple(kf.id for kf in self.observations)


def update_normals(points, force: bool = False) -> None:
    """Each point's mean viewing direction over its observing keyframes (for the viewing-angle test of the search).

    Recomputed where the observing keyframes changed (or `force`, after a loop correction moved the points); the
    small moves of a local BA do not matter to a 60-degree viewing-angle test. Points with the same number of
    observers are done in one batch.
    """
    stale: dict[int, list[MapPoint]] = {}
    for p in points:
        key = tuple(kf.id for kf in p.observations)
        if key and (force or key != p._normal_key):
            p._normal_key = key
            stale.setdefault(len(key), []).append(p)
    observers = {kf for group in stale.values() for p in group for kf in p.observations}
    centres = {kf: kf.center for kf in observers}
    for group in stale.values():
        C = np.array([centres[kf] for p in group for kf in p.observations]).reshape(len(group), -1, 3)
        d = np.array([p.position for p in group])[:, None] - C
        d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
        n = d.sum(1)
        n /= np.maximum(np.sqrt((n * n).sum(1)), 1e-12)[:, None]
        for p, normal in zip(group, n, strict=True):
            p.normal = normal


def update_descriptors(points, binary: bool) -> None:
    """Each point's descriptor: the observation descriptor with the least median distance to the others (ORB-SLAM's
    choice), recomputed only where the observations changed. Points with the same number of observations are done
    in one batch (a keyframe's few thousand points: ~50 batched products instead of one small product per point).
    """
    stale: dict[int, list[MapPoint]] = {}
    for p in points:
        key = tuple((kf.id, i) for kf, i in p.observations.items())
        if key != p._descriptor_key and key:
            p._descriptor_key = key
            stale.setdefault(len(key), []).append(p)
    for n, group in stale.items():
        descs = np.array([kf.descriptors[i] for p in group for kf, i in p.observations.items()])
        descs = descs.reshape(len(group), n, -1)  # [points, observations, descriptor]
        if n < 3:
            best = np.full(len(group), n - 1)
        else:
            d = np.sort(_batched_distances(descs, binary), axis=2)
            best = np.argmin(d[:, :, (n - 1) // 2], axis=1)  # lower median, as ORB-SLAM
        for p, desc in zip(group, descs[np.arange(len(group)), best], strict=True):
            p.descriptor = desc


def _batched_distances(descs: np.ndarray, binary: bool) -> np.ndarray:
    """`descriptor_distances(a, a)` for each [n, D] set of a batch [B, n, D] -> [B, n, n] (float32)."""
    if binary:
        return np.bitwise_count(descs[:, :, None] ^ descs[:, None]).sum(-1, dtype=np.int32).astype(np.float32)
    a = descs.astype(np.float32, copy=False)
    sq = (a * a).sum(2)
    d2 = sq[:, :, None] + sq[:, None] - 2.0 * a @ a.transpose(0, 2, 1)
    return np.sqrt(np.maximum(d2, 0.0))


class Map:
    """One connected map. Several live in an Atlas (`ruslam.slam.atlas`); they share one lock."""

    def __init__(self, lock: threading.RLock | None = None, id: int = 0, numbering: Numbering | None = None):
        self.id = id
        self.numbering = numbering or Numbering()
        self.keyframes: list[KeyFrame] = []  # insertion order, culled ones removed
        self.points: set[MapPoint] = set()
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

    # --- keyframes -------------------------------------------------------------------------------------------
    def new_keyframe(self, frame: Frame) -> KeyFrame:
        kf = KeyFrame(frame, next(self.numbering.keyframes))
        self.add_keyframe(kf)
        return kf

    def add_keyframe(self, kf: KeyFrame) -> None:
        self.keyframes.append(kf)
        self.covisibility[kf] = {}
        kf.map = self

    def update_connections(self, kf: KeyFrame, min_weight: int = 15) -> None:
        """Covisibility weights = number of shared map points; spanning-tree parent = strongest older neighbour."""
        counts: dict[KeyFrame, int] = {}
        for p in kf.points:
            if p is None or p.is_bad:
                continue
            for other in p.observations:
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
        for i, p in enumerate(kf.points):
            if p is not None:
                p.observations.pop(kf, None)
                if len(p.observations) < 2 and not p.is_bad:
                    self.remove_point(p)
            kf.points[i] = None
        for child in self.children(kf):
            child.parent = kf.parent
        kf.T_parent = kf.T_cw @ inverse_pose(kf.parent.T_cw)
        kf.T_parent_scale = kf.parent.current_scale()
        for o in self.covisibility.pop(kf, {}):
            self.covisibility.get(o, {}).pop(kf, None)
        kf.is_bad = True
        self.keyframes.remove(kf)

    # --- points ----------------------------------------------------------------------------------------------
    def new_point(self, position: np.ndarray, descriptor: np.ndarray, reference: KeyFrame) -> MapPoint:
        p = MapPoint(position, descriptor, reference, next(self.numbering.points))
        self.add_point(p)
        return p

    def add_point(self, p: MapPoint) -> None:
        self.points.add(p)

    def remove_point(self, p: MapPoint) -> None:
        p.is_bad = True
        for kf, i in p.observations.items():
            if kf.points[i] is p:
                kf.points[i] = None
        p.observations = {}
        self.points.discard(p)

    def replace_point(self, old: MapPoint, new: MapPoint) -> None:
        """Merge a duplicate: `new` inherits every observation of `old` (fusion and loop correction)."""
        if old is new:
            return
        for kf, i in list(old.observations.items()):
            if kf in new.observations:
                kf.points[i] = None
            else:
                new.add_observation(kf, i)
        new.visible += old.visible
        new.found += old.found
        old.observations = {}
        old.is_bad = True
        old.replaced_by = new
        self.points.discard(old)
