"""Camera models of the SLAM: pinhole with radial-tangential distortion, and fisheye (Kannala-Brandt, AQUALOC harbor).

Projection and undistortion go through OpenCV (`cv2.projectPoints`, `cv2.undistortPoints`, `cv2.fisheye.*`) so the
conventions match the calibration tools that produced EuRoC/AQUALOC/TUM parameters. After `undistort_points`, pixel
coordinates follow the ideal pinhole `K` of the same camera, which is what the SLAM's geometry works in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from ruslam.errors import InputError, MissingInput

MODELS = ("pinhole", "fisheye")
# OpenCV's default of 5 fixed iterations leaves ~5 mpx error at the corners of strongly distorted EuRoC images.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)


@dataclass
class Camera:
    """Intrinsics of one camera. ``dist`` is [k1, k2, p1, p2(, k3)] for pinhole, [k1, k2, k3, k4] for fisheye."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray = field(default_factory=lambda: np.zeros(4))
    model: str = "pinhole"

    def __post_init__(self):
        if self.model not in MODELS:
            raise InputError(f"Camera model must be one of {MODELS}, got {self.model!r}.")
        self.dist = np.asarray(self.dist, dtype=np.float64).ravel()
        if self.model == "fisheye" and self.dist.size != 4:
            raise InputError(f"A fisheye (Kannala-Brandt) camera needs 4 coefficients k1..k4, got {self.dist.size}.")
        if self.model == "pinhole" and self.dist.size not in (0, 4, 5, 8):
            raise InputError(f"A pinhole camera needs 0, 4, 5 or 8 distortion coefficients, got {self.dist.size}.")
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise InputError(f"Camera size and focal lengths must be positive, got {self.width}x{self.height}, "
                             f"fx={self.fx}, fy={self.fy}.")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        return self.model == "fisheye" or bool(np.any(self.dist != 0))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """3-D points in the camera frame [N, 3] -> distorted pixel coordinates [N, 2] (points need z > 0)."""
        points = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros((0, 2))
        if not self.distorted:
            z = points[:, 2:3]
            return points[:, :2] / z * [self.fx, self.fy] + [self.cx, self.cy]
        zero = np.zeros(3)
        if self.model == "fisheye":
            uv, _ = cv2.fisheye.projectPoints(points[:, None, :], zero, zero, self.K, self.dist)
        else:
            uv, _ = cv2.projectPoints(points[:, None, :], zero, zero, self.K, self.dist)
        return uv.reshape(-1, 2)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels [N, 2] -> pixels of the ideal pinhole camera with the same ``K``."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if len(uv) == 0 or not self.distorted:
            return uv.copy()
        if self.model == "fisheye":
            out = cv2.fisheye.undistortPoints(uv[:, None, :], self.K, self.dist, None, None, self.K, UNDISTORT_CRITERIA)
        else:
            out = cv2.undistortPoints(uv[:, None, :], self.K, self.dist, None, None, self.K, UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)

    def contains(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (pixel centres at integers, borders at -0.5 and size-0.5)."""
        uv = np.asarray(uv).reshape(-1, 2)
        return ((uv[:, 0] >= -0.5 + margin) & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin) & (uv[:, 1] <= self.height - 0.5 - margin))

    def to_dict(self) -> dict:
        return {"model": self.model, "width": int(self.width), "height": int(self.height),
                "intrinsics": [float(self.fx), float(self.fy), float(self.cx), float(self.cy)],
                "distortion": [float(d) for d in self.dist]}

    @classmethod
    def from_dict(cls, d: dict, source: str = "calibration") -> Camera:
        """Build from our calibration dict (``model, width, height, intrinsics [fx fy cx cy], distortion``)."""
        missing = [k for k in ("width", "height", "intrinsics") if k not in d]
        if missing:
            raise InputError(f"{source} lacks {missing}; expected keys model, width, height, "
                             "intrinsics: [fx, fy, cx, cy], distortion: [...].")
        intr = list(d["intrinsics"])
        if len(intr) != 4:
            raise InputError(f"{source}: intrinsics must be [fx, fy, cx, cy], got {intr}.")
        model = {"radtan": "pinhole", "radial-tangential": "pinhole", "equidistant": "fisheye",
                 "kannalabrandt8": "fisheye", "kannala-brandt": "fisheye"}.get(str(d.get("model", "pinhole")).lower(),
                                                                                 str(d.get("model", "pinhole")).lower())
        return cls(int(d["width"]), int(d["height"]), *map(float, intr), dist=d.get("distortion") or [0, 0, 0, 0],
                   model=model)

    @classmethod
    def from_yaml(cls, path: str | Path) -> Camera:
        """Read our calibration yaml, or an ORB-SLAM3 settings file (``Camera.fx`` ... keys, OpenCV %YAML header)."""
        d = read_yaml(path)
        if "Camera.fx" in d:
            return _from_orbslam(d, str(path))
        return cls.from_dict(d, source=f"Calibration file {path}")


def read_yaml(path: str | Path) -> dict:
    """Plain or OpenCV-flavoured yaml (leading ``%YAML:1.0`` line) -> dict, with one clear error when unusable."""
    path = Path(path)
    if not path.is_file():
        raise MissingInput(f"Calibration file {path} does not exist.")
    text = path.read_text()
    if text.startswith("%YAML"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    text = text.replace("!!opencv-matrix", "")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise InputError(f"Calibration file {path} is not valid YAML ({err.__class__.__name__}).") from None
    if not isinstance(data, dict):
        raise InputError(f"Calibration file {path} must hold a mapping of keys, got {type(data).__name__}.")
    return data


def _from_orbslam(d: dict, source: str) -> Camera:
    fisheye = str(d.get("Camera.type", "PinHole")).lower().startswith("kannala")
    keys = ["Camera.k1", "Camera.k2", "Camera.k3", "Camera.k4"] if fisheye else \
        ["Camera.k1", "Camera.k2", "Camera.p1", "Camera.p2", "Camera.k3"]
    try:
        dist = [float(d.get(k, 0.0)) for k in keys]
        return Camera(int(d["Camera.width"]), int(d["Camera.height"]), float(d["Camera.fx"]), float(d["Camera.fy"]),
                      float(d["Camera.cx"]), float(d["Camera.cy"]), dist=dist,
                      model="fisheye" if fisheye else "pinhole")
    except KeyError as err:
        raise InputError(f"{source} lacks {err.args[0]} (ORB-SLAM3 camera settings).") from None
