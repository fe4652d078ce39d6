"""Sequence readers: EuRoC ASL, AQUALOC (harbor / archaeological), TUM RGB-D and a plain image folder.

Every reader returns the same `Sequence` (timestamps in seconds, one `Camera` per image stream, optional stereo
extrinsics and ground truth as T_world_cam0), so the SLAM and the evaluation never see a dataset's layout.
Layouts are described in docs/data.md; every missing or malformed file raises one sentence naming it.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ruslam.atomic_files import atomic_path
from ruslam.data.camera import Camera, read_yaml
from ruslam.errors import InputError, MissingInput

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


class FrameReadError(InputError):
    """A frame file is missing or cannot be decoded; the SLAM may skip the frame with a warning."""


@dataclass
class Trajectory:
    """Timestamps [N] (seconds) and poses [N, 4, 4] (T_world_cam)."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self):
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).ravel()
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError(f"Trajectory has {len(self.timestamps)} timestamps but {len(self.poses)} poses.")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum()) if len(self) > 1 else 0.0


@dataclass
class Sequence:
    """An image sequence: ``image_paths[i][c]`` is frame i of camera c (c = 0 left/mono, 1 right)."""

    name: str
    cameras: list[Camera]
    timestamps: np.ndarray
    image_paths: list[list[Path]]
    T_cam0_cam1: np.ndarray | None = None
    groundtruth: Trajectory | None = None

    def __post_init__(self):
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).ravel()
        if len(self.image_paths) == 0:
            raise InputError(f"Sequence {self.name!r} has no frames.")
        if len(self.timestamps) != len(self.image_paths):
            raise InputError(f"Sequence {self.name!r}: {len(self.timestamps)} timestamps for "
                             f"{len(self.image_paths)} frames.")
        if np.any(np.diff(self.timestamps) <= 0):
            raise InputError(f"Sequence {self.name!r}: timestamps must increase strictly.")
        if any(len(p) != len(self.cameras) for p in self.image_paths):
            raise InputError(f"Sequence {self.name!r}: every frame needs one image per camera ({len(self.cameras)}).")
        if len(self.cameras) == 2 and self.T_cam0_cam1 is None:
            raise InputError(f"Stereo sequence {self.name!r} needs T_cam0_cam1.")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def stereo(self) -> bool:
        return len(self.cameras) == 2

    def subset(self, indices) -> Sequence:
        """The frames `indices` only (a camera that dropped frames); cameras and ground truth unchanged."""
        keep = list(indices)
        return Sequence(name=self.name, cameras=self.cameras, timestamps=self.timestamps[keep],
                        image_paths=[self.image_paths[i] for i in keep], T_cam0_cam1=self.T_cam0_cam1,
                        groundtruth=self.groundtruth)

    def load(self, i: int) -> list[np.ndarray]:
        """Frame i as one uint8 image per camera (HxW grey, or HxWx3 RGB for colour files)."""
        return [load_image(p) for p in self.image_paths[i]]


def load_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if Path(path).is_file() else None
    if image is None or image.size == 0:
        raise FrameReadError(f"Frame {path} is missing or cannot be decoded as an image.")
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise FrameReadError(f"Frame {path} has pixel type {image.dtype}; expected 8- or 16-bit.")
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if image.ndim == 3:
        image = np.ascontiguousarray(image[..., ::-1])  # OpenCV BGR -> RGB
    return image


def poses_from_quaternions(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """[N,3] translations + [N,4] quaternions (x, y, z, w) -> [N,4,4]."""
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(q_xyzw).as_matrix()
    poses[:, :3, 3] = t
    return poses


def _numeric_rows(path: Path, delimiter: str | None, min_cols: int) -> np.ndarray:
    """Numeric table of a text file, skipping comment/header lines; one clear error otherwise."""
    if not path.is_file():
        raise MissingInput(f"File {path} does not exist.")
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p for p in (line.split(delimiter) if delimiter else line.replace(",", " ").split()) if p.strip()]
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            if rows:
                raise InputError(f"{path}: non-numeric row {line[:60]!r}.") from None
            continue  # a header row
    if not rows or min(len(r) for r in rows) < min_cols:
        raise InputError(f"{path} holds no rows of at least {min_cols} numbers.")
    return np.array([r[:min_cols] for r in rows])


def read_tum_trajectory(path: str | Path) -> Trajectory:
    """TUM format ``timestamp tx ty tz qx qy qz qw`` (space or comma separated)."""
    a = _numeric_rows(Path(path), None, 8)
    return Trajectory(a[:, 0], poses_from_quaternions(a[:, 1:4], a[:, 4:8]))


def write_tum_trajectory(path: str | Path, trajectory: Trajectory) -> None:
    """TUM format ``timestamp tx ty tz qx qy qz qw`` by evo's writer (the files evo_ape reads), through a
    temporary file so an interrupted run leaves no partial file. An empty trajectory is refused: evo cannot read a
    TUM file without a pose."""
    from evo.core.trajectory import PoseTrajectory3D  # noqa: PLC0415 (evo only when writing)
    from evo.tools.file_interface import write_tum_trajectory_file  # noqa: PLC0415

    if len(trajectory) == 0:
        raise ValueError(f"Trajectory for {path} has no pose; not writing a TUM file evo could not read.")
    with atomic_path(path) as tmp:
        write_tum_trajectory_file(tmp, PoseTrajectory3D(poses_se3=list(trajectory.poses),
                                                        timestamps=trajectory.timestamps))


def read_euroc_groundtruth(path: str | Path, T_body_cam: np.ndarray | None = None) -> Trajectory:
    """ASL ground truth csv (``t_ns, p xyz, q wxyz, ...``) -> T_world_cam = T_world_body · T_body_cam."""
    a = _numeric_rows(Path(path), ",", 8)
    poses = poses_from_quaternions(a[:, 1:4], a[:, [5, 6, 7, 4]])
    if T_body_cam is not None:
        poses = poses @ T_body_cam
    return Trajectory(a[:, 0] * 1e-9, poses)


# ----------------------------------------------------------------------------------------------------- EuRoC


def _euroc_camera(cam_dir: Path) -> tuple[Camera, np.ndarray]:
    sensor = read_yaml(cam_dir / "sensor.yaml")
    try:
        T_BS = np.array(sensor["T_BS"]["data"], dtype=np.float64).reshape(4, 4)
        model = "fisheye" if sensor.get("distortion_model", "radial-tangential") == "equidistant" else "pinhole"
        camera = Camera(*map(int, sensor["resolution"]), *map(float, sensor["intrinsics"]),
                        dist=sensor.get("distortion_coefficients", [0, 0, 0, 0]), model=model)
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{cam_dir / 'sensor.yaml'} lacks a usable T_BS/resolution/intrinsics ({err}).") from None
    return camera, T_BS


def _euroc_images(cam_dir: Path) -> dict[int, Path]:
    path = cam_dir / "data.csv"
    if not path.is_file():
        raise MissingInput(f"EuRoC image list {path} does not exist (expected mav0/camX/data.csv).")
    out = {}
    with path.open() as f:
        for row in csv.reader(f):
            if not row or row[0].lstrip().startswith("#"):
                continue
            if len(row) < 2 or not row[0].strip().isdigit():
                raise InputError(f"{path}: expected rows 'timestamp_ns,filename', got {','.join(row)[:60]!r}.")
            out[int(row[0])] = cam_dir / "data" / row[1].strip()
    if not out:
        raise InputError(f"EuRoC image list {path} lists no images.")
    return out


def read_euroc(root: str | Path, stereo: bool = True, name: str | None = None) -> Sequence:
    """EuRoC ASL folder (the sequence folder holding ``mav0/``, or ``mav0`` itself)."""
    root = Path(root)
    mav0 = root / "mav0" if (root / "mav0").is_dir() else root
    if not (mav0 / "cam0").is_dir():
        raise MissingInput(f"{root} is not a EuRoC sequence: {mav0 / 'cam0'} does not exist.")
    cam_ids = ["cam0", "cam1"] if stereo else ["cam0"]
    cams, T_BS, images = [], [], []
    for cid in cam_ids:
        cam, T = _euroc_camera(mav0 / cid)
        cams.append(cam)
        T_BS.append(T)
        images.append(_euroc_images(mav0 / cid))
    stamps = sorted(set.intersection(*(set(im) for im in images)))
    if not stamps:
        raise InputError(f"{mav0}: cam0 and cam1 share no timestamps.")
    gt_path = mav0 / "state_groundtruth_estimate0" / "data.csv"
    gt = read_euroc_groundtruth(gt_path, T_BS[0]) if gt_path.is_file() else None
    return Sequence(name=name or (root.name if root.name != "mav0" else root.parent.name), cameras=cams,
                    timestamps=np.array(stamps, dtype=np.float64) * 1e-9,
                    image_paths=[[im[t] for im in images] for t in stamps],
                    T_cam0_cam1=np.linalg.inv(T_BS[0]) @ T_BS[1] if stereo else None, groundtruth=gt)


# --------------------------------------------------------------------------------------------------- AQUALOC

#: Calibrations quoted by ORB_SLAM3_AQUALOC "from AQUALOC calibration files" (see SOURCES.md).
AQUALOC_CAMERAS = {
    "harbor": Camera(640, 512, 256.214, 256.571, 330.685, 261.372,
                     dist=[-0.0626187, 0.0174982, -0.0102171, 0.00198907], model="fisheye"),
    "archaeo": Camera(968, 608, 519.538, 519.846, 481.444, 316.168, dist=[-0.207478, 0.0540258, 0.0, 0.0]),
}


def read_aqualoc(root: str | Path, site: str = "harbor", groundtruth: str | Path | None = None,
                 calibration: str | Path | None = None, name: str | None = None) -> Sequence:
    """AQUALOC sequence folder: an image csv (``*img*sequence*.csv``: ``timestamp_ns,image_name`` after a header)
    and the images in that folder or an ``*images*`` subfolder. Ground truth (``image_index tx ty tz qx qy qz qw``)
    is indexed by image number = row of the image csv; default: a ``*colmap_traj*`` file, rescaled ``new_`` first.
    """
    root = Path(root)
    if site not in AQUALOC_CAMERAS:
        raise InputError(f"AQUALOC site must be one of {sorted(AQUALOC_CAMERAS)}, got {site!r}.")
    if not root.is_dir():
        raise MissingInput(f"AQUALOC sequence folder {root} does not exist.")
    csvs = sorted(p for p in root.rglob("*.csv") if "img" in p.name.lower())
    if not csvs:
        raise MissingInput(f"{root} holds no AQUALOC image list (a '*img*sequence*.csv' file).")
    list_path = csvs[0]
    stamps, names = [], []
    with list_path.open() as f:
        for row in csv.reader(f):
            if len(row) >= 2 and row[0].strip().isdigit():
                stamps.append(int(row[0]))
                names.append(row[1].strip())
    if not names:
        raise InputError(f"AQUALOC image list {list_path} has no 'timestamp_ns,image_name' rows.")
    folders = [list_path.parent] + sorted(d for d in root.rglob("*") if d.is_dir() and "image" in d.name.lower())
    folder = next((d for d in folders if (d / names[0]).is_file()), None)
    if folder is None:
        raise MissingInput(f"AQUALOC image {names[0]} (first row of {list_path}) is in none of "
                                f"{[str(d) for d in folders]}.")
    camera = Camera.from_yaml(calibration) if calibration else AQUALOC_CAMERAS[site]
    timestamps = np.array(stamps, dtype=np.float64) * 1e-9
    if groundtruth is None:
        found = sorted(root.rglob("*colmap_traj*.txt"), key=lambda p: (not p.name.startswith("new_"), p.name))
        groundtruth = found[0] if found else None
    gt = None
    if groundtruth is not None:
        a = _numeric_rows(Path(groundtruth), None, 8)
        index = np.rint(a[:, 0]).astype(int)
        if index.min() < 0 or index.max() >= len(timestamps):
            raise InputError(f"Ground truth {groundtruth} indexes image {index.max()} but {list_path} lists "
                             f"{len(timestamps)} images.")
        gt = Trajectory(timestamps[index], poses_from_quaternions(a[:, 1:4], a[:, 4:8]))
    return Sequence(name=name or root.name, cameras=[camera], timestamps=timestamps,
                    image_paths=[[folder / n] for n in names], groundtruth=gt)


# ------------------------------------------------------------------------------------------------------- TUM

TUM_CAMERAS = {  # ROS default calibrations of the TUM RGB-D benchmark (colour camera)
    "freiburg1": Camera(640, 480, 517.3, 516.5, 318.6, 255.3, dist=[0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    "freiburg2": Camera(640, 480, 520.9, 521.0, 325.1, 249.7, dist=[0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    "freiburg3": Camera(640, 480, 535.4, 539.2, 320.1, 247.6),
}


def read_tum(root: str | Path, calibration: str | Path | None = None, name: str | None = None) -> Sequence:
    """TUM RGB-D folder (``rgb.txt``: ``timestamp rgb/<file>``; optional ``groundtruth.txt``); monocular RGB.
    The camera is taken from ``calibration`` or from 'freiburgN' in the folder name."""
    root = Path(root)
    list_path = root / "rgb.txt"
    if not list_path.is_file():
        raise MissingInput(f"{root} is not a TUM RGB-D sequence: {list_path} does not exist.")
    stamps, paths = [], []
    for line in list_path.read_text().splitlines():
        parts = line.split()
        if len(parts) >= 2 and not line.startswith("#"):
            stamps.append(float(parts[0]))
            paths.append([root / parts[1]])
    if not paths:
        raise InputError(f"TUM image list {list_path} lists no images.")
    if calibration:
        camera = Camera.from_yaml(calibration)
    else:
        key = next((k for k in TUM_CAMERAS if k in root.name), None)
        if key is None:
            raise InputError(f"Cannot tell the TUM camera of {root.name!r} (no 'freiburg1/2/3' in the name); "
                             "pass calibration=<yaml>.")
        camera = TUM_CAMERAS[key]
    gt_path = root / "groundtruth.txt"
    return Sequence(name=name or root.name, cameras=[camera], timestamps=np.array(stamps), image_paths=paths,
                    groundtruth=read_tum_trajectory(gt_path) if gt_path.is_file() else None)


# ------------------------------------------------------------------------------------------ plain image folder


def read_image_folder(root: str | Path, calibration: str | Path | None = None, fps: float | None = None,
                      groundtruth: str | Path | None = None, name: str | None = None) -> Sequence:
    """Images sorted by name + a calibration yaml (default ``<root>/calibration.yaml``: model, width, height,
    intrinsics, distortion, optional fps). Timestamps: numeric file stems (ns if > 1e12), else frame / fps."""
    root = Path(root)
    if not root.is_dir():
        raise MissingInput(f"Image folder {root} does not exist.")
    files = sorted((p for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
    if not files:
        raise InputError(f"Image folder {root} holds no images ({', '.join(IMAGE_SUFFIXES)}).")
    calibration = Path(calibration) if calibration else root / "calibration.yaml"
    if not calibration.is_file():
        raise MissingInput(f"Calibration file {calibration} does not exist; write one with keys model, width, "
                                "height, intrinsics: [fx, fy, cx, cy], distortion: [...].")
    camera = Camera.from_yaml(calibration)
    fps = fps or read_yaml(calibration).get("fps") or 20.0
    stems = [p.stem for p in files]
    if all(re.fullmatch(r"\d+(\.\d+)?", s) for s in stems) and len(set(map(float, stems))) == len(stems):
        stamps = np.array([float(s) for s in stems])
        stamps = stamps * 1e-9 if stamps.max() > 1e12 else stamps
    else:
        stamps = np.arange(len(files)) / float(fps)
    gt = read_tum_trajectory(groundtruth) if groundtruth else None
    return Sequence(name=name or root.name, cameras=[camera], timestamps=stamps, image_paths=[[p] for p in files],
                    groundtruth=gt)


def _natural_key(path: Path):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]
