"""A folder of colour images paired with depth maps, e.g. your own RGB-D captures or exported dataset samples.

Two layouts are recognised:

- **sub-folders**: ``color/`` (or ``rgb/``, ``image/``, ``images/``) and ``depth/``, paired by file stem
  (``color/1.png`` + ``depth/1.pgm``);
- **flat**: depth files whose stem starts with ``depth`` next to colour files, paired by the rest of the stem
  (``img42.jpg`` / ``rgb_42.png`` / ``42.png`` + ``depth42.csv`` / ``depth_42.png``).

Depth encodings: integer images (16-bit PNG/PGM/TIFF) are divided by ``depth_scale`` (1000 = millimetres as in
slambook/Redwood, 5000 for TUM); ``.npy``, ``.csv`` and float TIFFs are metres.  0, negative, NaN and inf become
NaN (`make_sample`).  TUM folders (``rgb/`` + ``depth/`` named by timestamps that differ slightly) pair by
nearest timestamp with ``max_time_diff=0.02`` (the rule of TUM's ``associate.py``).  Ids are the colour keys.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from ruslam.data.rgbd_sample import make_sample
from ruslam.errors import InputError, MissingInput

COLOUR_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".bmp", ".tif", ".tiff")
DEPTH_SUFFIXES = (".png", ".pgm", ".tif", ".tiff", ".npy", ".csv")
COLOUR_DIRS = ("color", "colour", "rgb", "image", "images")
_COLOUR_PREFIX = re.compile(r"^(img|image|rgb|color|colour)[_\-]?", re.IGNORECASE)
_DEPTH_PREFIX = re.compile(r"^depth[_\-]?", re.IGNORECASE)


def _files(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)


def _natural(key: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key)]


def associate_by_time(colours: dict[str, Path], depths: dict[str, Path], max_time_diff: float,
                      root: Path) -> list[tuple[str, Path, Path]]:
    """TUM ``associate.py`` rule: keys are timestamps (s); candidate pairs closer than ``max_time_diff`` are
    matched greedily, closest first, each file used once; colour frames left without depth are dropped."""
    try:
        tc = {k: float(k) for k in colours}
        td = {k: float(k) for k in depths}
    except ValueError:
        raise InputError(f"RGB-D folder {root}: max_time_diff needs file names that are timestamps in seconds "
                         f"(e.g. 1305031102.175304.png); got names like {next(iter(colours))!r}.") from None
    d_keys = sorted(td, key=td.get)
    d_times = np.array([td[k] for k in d_keys])
    candidates = []  # only depth stamps inside each colour stamp's window: linear in the sequence length
    for a, t in tc.items():
        lo, hi = np.searchsorted(d_times, [t - max_time_diff, t + max_time_diff])
        gaps = np.abs(t - d_times[lo:hi])
        candidates += [(g, a, d_keys[lo + j]) for j, g in enumerate(gaps) if g < max_time_diff]
    candidates.sort()
    used_c, used_d, pairs = set(), set(), []
    for _, a, b in candidates:
        if a not in used_c and b not in used_d:
            used_c.add(a), used_d.add(b), pairs.append((a, colours[a], depths[b]))
    if not pairs:
        raise InputError(f"RGB-D folder {root}: no colour/depth timestamps within {max_time_diff} s of each other.")
    return sorted(pairs, key=lambda p: tc[p[0]])


def find_pairs(root: Path, max_time_diff: float | None = None) -> list[tuple[str, Path, Path]]:
    """(key, colour path, depth path) of every pair in ``root``; unpaired files are an error unless pairing is
    by nearest timestamp (``max_time_diff`` seconds, TUM style)."""
    colour_dir = next((root / d for d in COLOUR_DIRS if (root / d).is_dir()), None)
    if colour_dir is not None and (root / "depth").is_dir():
        colours = {p.stem: p for p in _files(colour_dir, COLOUR_SUFFIXES)}
        depths = {p.stem: p for p in _files(root / "depth", DEPTH_SUFFIXES)}
    else:
        files = _files(root, COLOUR_SUFFIXES + DEPTH_SUFFIXES)
        depths = {_DEPTH_PREFIX.sub("", p.stem): p for p in files if _DEPTH_PREFIX.match(p.stem)}
        colours = {_COLOUR_PREFIX.sub("", p.stem): p for p in files
                   if not _DEPTH_PREFIX.match(p.stem) and p.suffix.lower() in COLOUR_SUFFIXES}
    if not colours and not depths:
        raise InputError(f"RGB-D folder {root} holds no colour/depth pairs; expected color/ + depth/ sub-folders "
                         f"or files like img1.jpg + depth1.png.")
    if max_time_diff is not None and colours and depths:
        return associate_by_time(colours, depths, max_time_diff, root)
    unpaired = sorted(str(p) for k, p in colours.items() if k not in depths)
    unpaired += sorted(str(p) for k, p in depths.items() if k not in colours)
    if unpaired:
        raise InputError(f"RGB-D folder {root} has {len(unpaired)} file(s) without a colour/depth partner, "
                         f"e.g. {unpaired[0]}; every colour image needs a depth file with the same key "
                         f"(TUM-style timestamps: set max_time_diff).")
    return [(k, colours[k], depths[k]) for k in sorted(colours, key=_natural)]


def read_colour(path: Path) -> np.ndarray:
    """8-bit RGB HxWx3 (alpha dropped); grayscale and 16-bit colour images are refused."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"Colour image {path} cannot be read as an image.")
    if image.ndim == 2 or image.shape[2] == 1:
        raise InputError(f"Colour image {path} is grayscale; an RGB colour image is expected.")
    if image.dtype != np.uint8:
        raise InputError(f"Colour image {path} is {image.dtype} ({8 * image.itemsize}-bit); 8-bit RGB is expected.")
    return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)


def read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """Depth in metres (invalid values untouched; `make_sample` marks them)."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            depth = np.load(path, allow_pickle=False)
        elif suffix == ".csv":
            depth = np.loadtxt(path, delimiter=",", dtype=np.float32, ndmin=2)
        else:
            depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if depth is None:
                raise InputError("unreadable")
    except (ValueError, OSError, EOFError) as err:
        raise InputError(f"Depth file {path} cannot be read as a depth map ({err}).") from None
    if depth.ndim != 2:
        raise InputError(f"Depth file {path} must hold one HxW channel, got shape {depth.shape}.")
    if depth.dtype == np.uint8:
        raise InputError(f"Depth file {path} is 8-bit, which cannot hold metric depth; expected 16-bit integers "
                         f"(scaled by depth_scale) or metres in .npy/.csv/float TIFF.")
    if np.issubdtype(depth.dtype, np.integer):
        return depth.astype(np.float32) / np.float32(depth_scale)
    if not np.issubdtype(depth.dtype, np.floating):
        raise InputError(f"Depth file {path} has dtype {depth.dtype}; expected integers or floats.")
    return depth.astype(np.float32)


class RGBDFolder:
    """Map-style RGB-D dataset over a folder; ``ds[i]`` -> ``{"id", "image", "depth"}`` in key order."""

    def __init__(self, root: str | Path, depth_scale: float = 1000.0, max_time_diff: float | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise MissingInput(f"RGB-D folder {self.root} does not exist.")
        if not depth_scale > 0:
            raise InputError(f"depth_scale must be positive (1000 for millimetres, 5000 for TUM), got {depth_scale}.")
        self.depth_scale = float(depth_scale)
        if max_time_diff is not None and not max_time_diff > 0:
            raise InputError(f"max_time_diff must be positive seconds (TUM uses 0.02), got {max_time_diff}.")
        self.pairs = find_pairs(self.root, max_time_diff)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> dict:
        if not -len(self) <= i < len(self):
            raise IndexError(f"RGB-D folder index {i} is out of range for {len(self)} pairs.")
        key, colour, depth = self.pairs[i]
        return make_sample(key, read_colour(colour), read_depth(depth, self.depth_scale), source=str(depth))
