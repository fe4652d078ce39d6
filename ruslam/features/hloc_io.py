"""hloc's file conventions: ``features.h5``, ``pairs.txt`` and ``matches.h5``, written and read back.

What hloc (cvg/Hierarchical-Localization) writes and its readers expect, as checked in its source
(``extract_features.py``, ``match_features.py``, ``utils/io.py``, ``utils/parsers.py``, ``reconstruction.py``):

- ``features.h5``: one group per image, named by the image path relative to the image folder (``a/b.jpg``: nested
  groups ``a`` then ``b.jpg``). In it ``keypoints`` [N, 2] (x, y) in pixels of the original image with the centre
  of the top-left pixel at (0, 0) (hloc maps keypoints back with ``(x + 0.5) * s - 0.5`` and adds 0.5 only when it
  imports them into COLMAP, whose origin is the top-left corner), ``scores`` [N], ``descriptors`` [D, N]
  (transposed), ``image_size`` [2] = (width, height). hloc stores every float32 array as float16 by default;
  here descriptors and scores are float16, keypoints stay float32 (float16 has 0.5 px steps past 1024 px), which
  hloc's readers accept (they cast). Extra keys (``global_descriptor``) are ignored by hloc's local-feature
  readers, and ``global_descriptor`` is the key hloc's ``pairs_from_retrieval`` reads.
- ``pairs.txt``: one ``name0 name1`` per line, the names of features.h5.
- ``matches.h5``: one group per pair named ``names_to_pair(name0, name1)`` =
  ``name0.replace('/', '-') + '/' + name1.replace('/', '-')`` (hloc's current format, a nested group; its
  readers also accept the older ``'_'`` separator and the reversed order), holding ``matches0`` [N0] int16
  (index into image 1's keypoints, -1 = unmatched; int32 when image 1 has more than 32767 keypoints) and
  ``matching_scores0`` [N0] float16.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from ruslam.errors import InputError, MissingInput


def names_to_pair(name0: str, name1: str, separator: str = "/") -> str:
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def write_feature_group(fd: h5py.File, name: str, pred: dict, image_size: tuple[int, int],
                        half: bool = True) -> None:
    """One image's features into an open file: ``pred`` as `Extractor.extract` returns it (descriptors [N, D])."""
    if name in fd:
        del fd[name]
    grp = fd.create_group(name)
    desc = np.asarray(pred["descriptors"])
    if desc.dtype != np.uint8:  # binary descriptors (ORB) stay packed bytes
        desc = desc.astype(np.float16 if half else np.float32)
    grp.create_dataset("keypoints", data=np.asarray(pred["keypoints"], np.float32).reshape(-1, 2))
    grp.create_dataset("scores", data=np.asarray(pred["scores"]).astype(np.float16 if half else np.float32))
    width = desc.shape[-1] if desc.ndim == 2 else 0  # an image without keypoints: [N=0, D] or an empty array
    grp.create_dataset("descriptors", data=np.ascontiguousarray(desc.reshape(len(desc), width).T))
    grp.create_dataset("image_size", data=np.asarray(image_size, np.int64))
    if pred.get("global_descriptor") is not None:
        grp.create_dataset("global_descriptor",
                           data=np.asarray(pred["global_descriptor"]).astype(np.float16 if half else np.float32))


def list_feature_names(path: str | Path) -> list[str]:
    """Image names of a features.h5 (groups that hold a ``keypoints`` dataset), in file order."""
    names: list[str] = []
    with open_h5(path) as fd:
        fd.visititems(lambda key, obj: names.append(key.rsplit("/", 1)[0] if "/" in key else "")
                      if isinstance(obj, h5py.Dataset) and key.rsplit("/", 1)[-1] == "keypoints" else None)
    return [n for n in names if n]


def open_h5(path: str | Path, what: str = "HDF5 file") -> h5py.File:
    path = Path(path)
    if not path.is_file():
        raise MissingInput(f"{what} {path} does not exist.")
    try:
        return h5py.File(path, "r")
    except OSError:
        raise InputError(f"{path} is not a readable HDF5 file.") from None


def read_features(path: str | Path, name: str) -> dict[str, np.ndarray]:
    """One image's features as arrays: keypoints [N, 2] float32, scores [N], descriptors [N, D] (back to rows),
    image_size (w, h), and global_descriptor when stored."""
    with open_h5(path, "Features file") as fd:
        if name not in fd or "keypoints" not in fd[name]:
            raise InputError(f"Features file {path} has no image {name!r}.")
        grp = fd[name]
        out = {k: grp[k][()] for k in grp}
    out["keypoints"] = out["keypoints"].astype(np.float32)
    out["descriptors"] = out["descriptors"].T
    return out


def write_matches_group(fd: h5py.File, name0: str, name1: str, matches0: np.ndarray, scores0: np.ndarray,
                        num_keypoints1: int) -> None:
    pair = names_to_pair(name0, name1)
    if pair in fd:
        del fd[pair]
    grp = fd.create_group(pair)
    grp.create_dataset("matches0", data=np.asarray(matches0).astype(np.int16 if num_keypoints1 < 32768 else np.int32))
    grp.create_dataset("matching_scores0", data=np.asarray(scores0).astype(np.float16))


def read_matches(path: str | Path, name0: str, name1: str) -> tuple[np.ndarray, np.ndarray]:
    """Matches of a pair as [M, 2] index pairs (image 0, image 1) and their scores [M], whichever order and
    separator the pair was stored under (as hloc's ``find_pair``)."""
    with open_h5(path, "Matches file") as fd:
        for separator in ("/", "_"):
            for a, b, reverse in ((name0, name1, False), (name1, name0, True)):
                pair = names_to_pair(a, b, separator)
                if pair in fd and "matches0" in fd[pair]:
                    m0 = fd[pair]["matches0"][()].astype(np.int64)
                    s0 = fd[pair]["matching_scores0"][()].astype(np.float32)
                    idx = np.flatnonzero(m0 != -1)
                    matches = np.stack([idx, m0[idx]], -1)
                    return (matches[:, ::-1].copy() if reverse else matches), s0[idx]
    raise InputError(f"Matches file {path} has no pair ({name0}, {name1}); match it with the same pairs file.")


def write_pairs(path: Path, pairs: list[tuple[str, str]]) -> None:
    path.write_text("".join(f"{a} {b}\n" for a, b in pairs))


def read_pairs(path: str | Path) -> list[tuple[str, str]]:
    path = Path(path)
    if not path.is_file():
        raise MissingInput(f"Pairs file {path} does not exist.")
    pairs = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise InputError(f"{path} line {i}: expected 'name0 name1', got {line[:80]!r}.")
        pairs.append((parts[0], parts[1]))
    if not pairs:
        raise InputError(f"Pairs file {path} lists no pairs.")
    return pairs
