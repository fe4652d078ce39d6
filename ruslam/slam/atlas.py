"""The Atlas (ORB-SLAM3): a list of maps, one active, plus the per-frame trajectory records of all of them.

When tracking is lost and relocalisation fails, the tracker starts a new map at once instead of waiting for the
camera to come back; the old map stays, inactive. Loop closing merges two maps when place recognition links a
keyframe of the active map to one of an inactive map (`merge`: the active map is moved into the other's frame by
a similarity, Sim3 in mono, SE3 in stereo). Every tracked frame is recorded against a reference keyframe, so its
pose follows later corrections; the reported trajectory is the map that holds the most frames (`trajectory`),
the other maps' frame counts are reported beside it, never aligned as if they were one piece.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from ruslam.slam.map import KeyFrame, Map, inverse_pose, scale_translation, transform


@dataclass
class Record:
    """A tracked frame: its pose relative to a reference keyframe, in the reference's scale `scale`."""

    index: int
    timestamp: float
    reference: KeyFrame
    T_cr: np.ndarray
    scale: float

    def T_cw(self) -> np.ndarray:
        ratio = self.reference.current_scale() / self.scale
        return scale_translation(self.T_cr, ratio) @ self.reference.pose()


class Atlas:
    def __init__(self, first: Map | None = None):
        self.lock = first.lock if first is not None else threading.RLock()
        self.maps: list[Map] = [first if first is not None else Map(self.lock, 0)]
        self.active: Map = self.maps[0]
        self.store = self.maps[0].store  # the points of every map
        self.records: list[Record] = []

    def new_map(self) -> Map:
        """Start an empty map and make it active; the previous one is kept (inactive) when it has keyframes."""
        with self.lock:
            if not self.active.keyframes:
                self.maps.remove(self.active)
            new = Map(self.lock, max(m.id for m in self.maps) + 1 if self.maps else 0, self.store,
                      self.active.keyframe_ids)
            self.maps.append(new)
            self.active = new
            return new

    def activate(self, m: Map) -> None:
        """Make an inactive map active again (relocalised in it); an empty active map is dropped."""
        with self.lock:
            if not self.active.keyframes and self.active is not m:
                self.maps.remove(self.active)
            self.active = m

    def inactive(self) -> list[Map]:
        return [m for m in self.maps if m is not self.active and m.keyframes]

    def record(self, index: int, timestamp: float, reference: KeyFrame, T_cw: np.ndarray) -> None:
        self.records.append(Record(index, timestamp, reference, T_cw @ inverse_pose(reference.T_cw),
                                   reference.current_scale()))

    # --- merging -----------------------------------------------------------------------------------------------
    def merge(self, moved: Map, target: Map, S: np.ndarray) -> None:
        """Move every keyframe and point of `moved` into `target` by S (x_target = S x_moved, [sR | t])."""
        with self.lock:
            s = float(np.cbrt(np.linalg.det(S[:3, :3])))
            S_inv = inverse_pose(S)
            for kf in moved.keyframes:
                T = kf.T_cw @ S_inv  # a similarity with scale 1/s
                kf.T_cw = _rigid(T)
                kf.scale *= s
                kf.map = target
            ids = moved.sorted_points()
            self.store.position[ids] = transform(S, self.store.position[ids])
            target.keyframes.extend(moved.keyframes)
            target.points |= moved.points
            target.covisibility.update(moved.covisibility)
            moved.keyframes, moved.points, moved.covisibility = [], set(), {}
            moved.merged_into = target
            self.maps.remove(moved)
            if self.active is moved:
                self.active = target

    # --- output ------------------------------------------------------------------------------------------------
    def frames_per_map(self) -> dict[Map, list[Record]]:
        out: dict[Map, list[Record]] = {}
        for r in self.records:
            out.setdefault(r.reference.map.resolved(), []).append(r)
        return out

    def trajectory(self) -> tuple[list[Record], np.ndarray, list[int]]:
        """(records of the map with the most frames, their poses T_world_cam [N, 4, 4], frame counts per map)."""
        groups = sorted(self.frames_per_map().values(), key=len, reverse=True)
        if not groups:
            return [], np.zeros((0, 4, 4)), []
        best = sorted(groups[0], key=lambda r: r.index)
        poses = np.stack([inverse_pose(r.T_cw()) for r in best])
        return best, poses, [len(g) for g in groups]


def _rigid(S: np.ndarray) -> np.ndarray:
    """[sR | t] -> [R | t/s]: the camera pose in the scale of the transformed map."""
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    out = np.eye(4)
    out[:3, :3] = S[:3, :3] / s
    out[:3, 3] = S[:3, 3] / s
    return out
