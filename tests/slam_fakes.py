"""Exact-geometry stand-ins for a sequence and an extractor, so the SLAM is tested without rendering.

A seafloor of random landmarks (each with its own descriptor) is seen by a camera flying a closed circuit; the
fake extractor reads the frame number written into the image and returns the true projections (plus pixel noise)
and the landmarks' descriptors. The global descriptor is a bag of landmark "words", so revisits look alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ruslam.data.readers import FrameReadError
from ruslam.slam.geometry import pose_matrix, project
from ruslam.slam.map import inverse_pose


@dataclass
class PinholeCamera:
    width: int = 640
    height: int = 480
    fx: float = 450.0
    fy: float = 450.0
    cx: float = 319.5
    cy: float = 239.5

    @property
    def K(self):
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def undistort_points(self, uv):
        return np.asarray(uv, np.float64).reshape(-1, 2).copy()


def circuit(num_frames: int, laps: float = 1.15, radii=(3.0, 2.0), altitude: float = 2.0) -> np.ndarray:
    """T_world_cam [N, 4, 4]: a downward-looking camera on an ellipse, heading along the path."""
    out = []
    for i in range(num_frames):
        a = 2 * np.pi * laps * i / num_frames
        c = np.array([radii[0] * np.cos(a), radii[1] * np.sin(a), altitude])
        forward = np.array([-radii[0] * np.sin(a), radii[1] * np.cos(a), 0.0])
        forward /= np.linalg.norm(forward)
        z = np.array([0.0, 0.0, -1.0])  # optical axis down
        y = -forward  # image "down" points backwards
        x = np.cross(y, z)
        out.append(pose_matrix(np.stack([x, y, z], 1), c))
    return np.stack(out)


class FakeSequence:
    def __init__(self, num_frames=120, stereo=False, baseline=0.12, seed=0, black=(), corrupt=(), laps=1.15,
                 landmarks=15000, radii=(3.0, 2.0), extent=6.5):
        rng = np.random.default_rng(seed)
        xy = rng.uniform(-extent, extent, (landmarks, 2))
        z = 0.15 * np.sin(xy[:, 0] * 1.3) * np.cos(xy[:, 1] * 0.9) + rng.uniform(-0.05, 0.05, landmarks)
        self.landmarks = np.c_[xy, z]
        self.name = "fake"
        self.cameras = [PinholeCamera()] * (2 if stereo else 1)
        self.T_cam0_cam1 = pose_matrix(np.eye(3), [baseline, 0, 0]) if stereo else None
        self.timestamps = np.arange(num_frames) / 10.0
        self.poses = circuit(num_frames, laps, radii)
        self.black, self.corrupt = set(black), set(corrupt)

    def __len__(self):
        return len(self.timestamps)

    def load(self, i):
        if i in self.corrupt:
            raise FrameReadError(f"Frame {i}.png is missing or cannot be decoded as an image.")
        images = []
        for c in range(len(self.cameras)):
            im = np.zeros((480, 640), np.uint8)
            if i not in self.black:
                im[0, :4] = np.frombuffer(np.uint32(i).tobytes(), np.uint8)
                im[0, 4] = c
                im[0, 5] = 1
            images.append(im)
        return images


def frame_number(image: np.ndarray) -> int:
    """The frame number FakeSequence writes into the first row of its images."""
    return int(np.frombuffer(image[0, :4].tobytes(), np.uint32)[0])


class FakeExtractor:
    """Projections of the landmarks for the frame whose number is written in the image."""

    def __init__(self, sequence: FakeSequence, binary=False, noise_px=0.5, dim=32, seed=1, words=4096, levels=1):
        rng = np.random.default_rng(seed)
        self.seq, self.binary, self.noise = sequence, binary, noise_px
        # a pyramid detector's: each landmark detected on one of `levels` levels (scale 1.2^level, noise with it)
        self.scales = 1.2 ** rng.integers(0, levels, len(sequence.landmarks))
        n = len(sequence.landmarks)
        if binary:
            self.desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        else:
            d = rng.normal(size=(n, dim)).astype(np.float32)
            self.desc = d / np.linalg.norm(d, axis=1, keepdims=True)
        self.words = rng.integers(0, words, n)
        self.num_words = words

    def extract(self, image):
        if image[0, 5] != 1:  # black frame: nothing to detect
            return {"keypoints": np.zeros((0, 2), np.float32), "scores": np.zeros(0, np.float32),
                    "descriptors": self.desc[:0], "global_descriptor": None}
        i = frame_number(image)
        cam = int(image[0, 4])
        T_cw = inverse_pose(self.seq.poses[i])
        if cam == 1:
            T_cw = inverse_pose(self.seq.T_cam0_cam1) @ T_cw
        K = self.seq.cameras[0].K
        uv, z = project(K, T_cw, self.seq.landmarks)
        rng = np.random.default_rng(1000 * i + cam)
        uv = uv + rng.normal(0, self.noise, uv.shape) * self.scales[:, None]
        vis = np.nonzero((z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < 639) & (uv[:, 1] < 479))[0]
        desc = self.desc[vis].copy()
        if self.binary:
            flips = rng.integers(0, 256, desc.shape[0])  # one random bit flipped per descriptor
            desc[np.arange(len(desc)), flips // 8] ^= (1 << (flips % 8)).astype(np.uint8)
        else:
            desc = desc + rng.normal(0, 0.05, desc.shape).astype(np.float32)
            desc /= np.linalg.norm(desc, axis=1, keepdims=True)
        g = np.bincount(self.words[vis], minlength=self.num_words).astype(np.float32)
        g /= max(np.linalg.norm(g), 1e-12)
        out = {"keypoints": uv[vis].astype(np.float32), "scores": np.ones(len(vis), np.float32),
               "descriptors": desc, "global_descriptor": g}
        return out if np.all(self.scales == 1) else {**out, "scales": self.scales[vis].astype(np.float32)}
