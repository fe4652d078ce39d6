"""OpenCV baselines (ORB, SIFT) behind the project's extractor contract."""

from __future__ import annotations

import cv2
import numpy as np

from ruslam.models.extractor import Extractor, to_uint8_gray
from ruslam.models.orbslam_keypoints import EDGE, PATCH_SIZE, orbslam_keypoints


def _keypoint_arrays(kps) -> tuple[np.ndarray, np.ndarray]:
    xy = np.array([kp.pt for kp in kps], dtype=np.float32).reshape(-1, 2)
    scores = np.array([kp.response for kp in kps], dtype=np.float32)
    return xy, scores


class ORB(Extractor):
    """ORB-SLAM's features: FAST + rBRIEF over an 8-level pyramid, 256-bit binary descriptors.

    ``distribution="orbslam"`` (default) chooses the keypoints as ORB-SLAM does (`orbslam_keypoints`: budget
    per level, grid FAST with an adaptive threshold, quadtree spreading, intensity-centroid orientation), then
    computes OpenCV's rBRIEF on them; ``"opencv"`` is plain ``cv2.ORB`` (strongest corners at one threshold).
    """

    default_conf = {"max_keypoints": 2000, "scale_factor": 1.2, "n_levels": 8, "fast_threshold": 20,
                    "min_fast_threshold": 7, "distribution": "orbslam"}
    binary = True

    def __init__(self, **conf):
        super().__init__(**conf)
        c = self.conf
        if c["distribution"] not in ("orbslam", "opencv"):
            raise ValueError(f"ORB distribution must be 'orbslam' or 'opencv', got {c['distribution']!r}.")
        self._orb = cv2.ORB_create(  # plain ORB, or only the rBRIEF of ORB-SLAM's keypoints (same border)
            nfeatures=c["max_keypoints"], scaleFactor=c["scale_factor"], nlevels=c["n_levels"],
            fastThreshold=c["fast_threshold"],
            **({"edgeThreshold": EDGE, "patchSize": PATCH_SIZE} if c["distribution"] == "orbslam" else {}),
        )

    def extract(self, image):
        gray = to_uint8_gray(image)
        c = self.conf
        if c["distribution"] == "opencv":
            kps, desc = self._orb.detectAndCompute(gray, None)
        else:
            kps = orbslam_keypoints(gray, c["max_keypoints"], c["n_levels"], c["scale_factor"],
                                    c["fast_threshold"], c["min_fast_threshold"])
            kps, desc = self._orb.compute(gray, kps) if kps else ((), None)
        xy, scores = _keypoint_arrays(kps)
        desc = np.zeros((0, 32), np.uint8) if desc is None else desc
        scales = np.array([c["scale_factor"] ** kp.octave for kp in kps], np.float32)
        return {"keypoints": xy, "scores": scores, "descriptors": desc, "scales": scales}


class SIFT(Extractor):
    """OpenCV SIFT, 128-d float descriptors L2-normalized."""

    default_conf = {"max_keypoints": 2000, "contrast_threshold": 0.04}

    def __init__(self, **conf):
        super().__init__(**conf)
        self._sift = cv2.SIFT_create(
            nfeatures=self.conf["max_keypoints"], contrastThreshold=self.conf["contrast_threshold"]
        )

    def extract(self, image):
        kps, desc = self._sift.detectAndCompute(to_uint8_gray(image), None)
        xy, scores = _keypoint_arrays(kps)
        if desc is None:
            desc = np.zeros((0, 128), np.float32)
        else:
            desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        n = self.conf["max_keypoints"]  # OpenCV may return a few more than asked on ties
        return {"keypoints": xy[:n], "scores": scores[:n], "descriptors": desc[:n].astype(np.float32)}
