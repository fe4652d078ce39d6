"""Weights files: a local path, or a URL + sha256 fetched once into a cache directory; strict, safe loading.

Nothing here downloads unless given a URL, and an offline machine gets one sentence saying where to put the file.
Checkpoints are always read with ``torch.load(..., weights_only=True)``: no code from a weights file is executed.
torch is imported only by the loaders, so a config check can resolve and hash a weights file before torch loads.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

from ruslam.atomic_files import atomic_path
from ruslam.errors import InputError, MissingWeights

if TYPE_CHECKING:
    import torch
    import torch.nn as nn

CACHE_ENV = "RUSLAM_CACHE"


def default_cache_dir() -> Path:
    """``$RUSLAM_CACHE/weights`` or ``~/.cache/ruslam/weights``."""
    root = os.environ.get(CACHE_ENV)
    return (Path(root) if root else Path.home() / ".cache" / "ruslam") / "weights"


def sha256_of(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _is_url(value: str) -> bool:
    return urlparse(value).scheme in ("http", "https", "file")


def resolve_weights(source: str | Path, sha256: str | None = None, cache_dir: str | Path | None = None) -> Path:
    """A local weights file for `source` (a path, or an http(s)/file URL downloaded once into `cache_dir`).

    With `sha256`, the file's hash is checked (a mismatching download is deleted, never kept).
    """
    source = str(source)
    if not _is_url(source):
        path = Path(source).expanduser()
        if not path.is_file():
            raise MissingWeights(f"Weights file {path} does not exist.")
        _check_hash(path, sha256)
        return path
    cache = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
    target = cache / Path(urlparse(source).path).name
    if target.is_file():
        _check_hash(target, sha256)
        return target
    try:
        with atomic_path(target) as tmp:  # a failed download or a wrong hash leaves no file behind
            with urllib.request.urlopen(source, timeout=30) as response, open(tmp, "wb") as out:
                shutil.copyfileobj(response, out)
            _check_hash(tmp, sha256, shown_as=source)
    except OSError as err:  # URLError, timeouts and disk errors are all OSErrors
        raise MissingWeights(
            f"Could not download weights from {source} ({err}); fetch the file on a machine with internet and put "
            f"it at {target} (or pass its local path)."
        ) from None
    return target


def _check_hash(path: Path, sha256: str | None, shown_as: str | None = None) -> None:
    if sha256 is None:
        return
    actual = sha256_of(path)
    if actual != sha256.lower():
        raise InputError(f"Weights file {shown_as or path} has sha256 {actual}, expected {sha256}.")


def load_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a state dict (plain, or wrapped as ``{"state_dict": ...}``) with ``weights_only=True``."""
    import torch  # noqa: PLC0415 (see the module docstring)

    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 (any unpickling failure is reported the same way)
        raise InputError(
            f"Weights file {path} is not a readable weights-only torch checkpoint ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''}); save just the state dict with torch.save."
        ) from None
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise InputError(f"Weights file {path} does not hold a state dict (a dict of name -> tensor).")
    return obj


def load_strict(module: nn.Module, state: dict[str, torch.Tensor], source: str | Path) -> None:
    """`module.load_state_dict(state, strict=True)`, with missing/unexpected/mis-shaped keys named in one sentence."""
    expected = module.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    shapes = [
        f"{k} {tuple(state[k].shape)} (expected {tuple(v.shape)})"
        for k, v in expected.items()
        if k in state and state[k].shape != v.shape
    ]
    if missing or unexpected or shapes:
        parts = [
            f"missing keys {missing}" if missing else "",
            f"unexpected keys {unexpected}" if unexpected else "",
            f"wrong shapes {shapes}" if shapes else "",
        ]
        raise InputError(
            f"Weights file {source} does not match {type(module).__name__}: " + "; ".join(p for p in parts if p) + "."
        )
    module.load_state_dict(state, strict=True)
