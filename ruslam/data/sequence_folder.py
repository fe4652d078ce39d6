"""Any folder of sequences: find every EuRoC / TUM RGB-D / image-folder sequence under a root and read it.

What makes a folder a sequence (checked in this order; a sequence's own sub-folders are not searched further):
- EuRoC ASL: ``mav0/cam0/`` (or ``cam0/data.csv`` when the folder is ``mav0`` itself); stereo with ``cam1``;
- TUM RGB-D: ``rgb.txt`` (+ ``groundtruth.txt``); the camera from ``calibration.yaml`` in the folder if present,
  else from 'freiburgN' in the folder name;
- image folder: ``calibration.yaml`` next to the images (+ optional ``groundtruth.txt`` in TUM format).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from ruslam.data.readers import IMAGE_SUFFIXES, Sequence, read_euroc, read_image_folder, read_tum
from ruslam.errors import InputError, MissingInput

log = logging.getLogger(__name__)
FORMATS = ("euroc", "tum", "image_folder")


def sequence_format(folder: Path) -> str | None:
    """'euroc', 'tum', 'image_folder', or None when ``folder`` is not a sequence."""
    if (folder / "mav0" / "cam0").is_dir() or (folder.name == "mav0" and (folder / "cam0" / "data.csv").is_file()):
        return "euroc"
    if (folder / "rgb.txt").is_file():
        return "tum"
    if (folder / "calibration.yaml").is_file() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir()):
        return "image_folder"
    return None


def find_sequences(root: str | Path, max_depth: int = 3) -> dict[str, str]:
    """{name: path relative to root} of every sequence at or under ``root`` (names are the relative paths, or the
    root's own name when the root is a sequence), sorted by name."""
    root = Path(root)
    if not root.is_dir():
        raise MissingInput(f"Sequence folder {root} does not exist (dataset.root=<folder of sequences>).")
    found = {}

    def visit(folder: Path, depth: int) -> None:
        if sequence_format(folder):
            rel = folder.relative_to(root).as_posix()
            found[root.name if rel == "." else rel] = rel
            return
        if depth < max_depth:
            for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
                visit(sub, depth + 1)

    visit(root, 0)
    if not found and any(p.suffix.lower() in IMAGE_SUFFIXES for p in root.iterdir()):
        raise MissingInput(f"{root / 'calibration.yaml'} is missing: an image folder needs the camera (model, width, "
                           "height, intrinsics: [fx, fy, cx, cy], distortion: [...]) next to its images.")
    if not found:
        raise MissingInput(f"No sequence found in {root} (searched {max_depth} levels deep): expected EuRoC "
                                "folders (mav0/cam0/), TUM RGB-D folders (rgb.txt) or image folders with a "
                                "calibration.yaml.")
    return dict(sorted(found.items()))


def read_sequence(path: str | Path, sensor: str = "mono", name: str | None = None, every: int = 1) -> Sequence:
    """The sequence in ``path`` whatever its format; ``sensor="stereo"`` uses a second camera where there is one.
    ``every=n`` keeps every n-th frame, a lower frame rate (the ground truth stays whole)."""
    if sensor not in ("mono", "stereo"):
        raise ValueError(f"sensor must be 'mono' or 'stereo', got {sensor!r}.")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise InputError(f"every must be a positive integer (keep every n-th frame), got {every!r}.")
    sequence = _read(Path(path), sensor == "stereo", name)
    if every == 1:
        return sequence
    return dataclasses.replace(sequence, timestamps=sequence.timestamps[::every],
                               image_paths=sequence.image_paths[::every])


def _read(path: Path, stereo: bool, name: str | None) -> Sequence:
    kind = sequence_format(path) if path.is_dir() else None
    if kind is None:
        raise MissingInput(f"{path} is not a sequence: expected a EuRoC folder (mav0/cam0/), a TUM RGB-D "
                                "folder (rgb.txt) or an image folder with a calibration.yaml.")
    name = name or path.resolve().name
    if kind == "euroc":
        mav0 = path / "mav0" if (path / "mav0").is_dir() else path
        has_right = (mav0 / "cam1" / "data.csv").is_file()
        if stereo and not has_right:
            log.warning("%s has no cam1: running it monocular.", path)
        return read_euroc(path, stereo=stereo and has_right, name=name)
    if stereo:
        log.warning("%s is a %s sequence (one camera): running it monocular.", path, kind)
    calibration = path / "calibration.yaml"
    if kind == "tum":
        return read_tum(path, calibration=calibration if calibration.is_file() else None, name=name)
    groundtruth = path / "groundtruth.txt"
    return read_image_folder(path, groundtruth=groundtruth if groundtruth.is_file() else None, name=name)
