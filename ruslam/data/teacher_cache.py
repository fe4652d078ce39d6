"""HDF5 cache of the frozen teachers' targets (hloc style), built once by a Lightning predict pass.

Layout of ``cache_dir``:

- ``teacher.json``: the teacher fingerprint (weights, VLAD codebook and the caller's settings hashed) and settings;
  a cache built by another teacher configuration is refused.
- ``shard-rank<r>-<uuid>.h5``: committed shards (``libver="latest"``), one group per image id (``/`` escaped
  as ``%2F``), one chunked, compressed dataset per key (``keypoint_logits`` [65, h, w], ``dense_descriptors`` [D, h, w],
  ``global_descriptor`` [G]), optionally float16; the fingerprint is also in each shard's attributes.
- ``.tmp-<host>-<pid>-<uuid>.h5``: the shard a running process is filling. It is closed and renamed to ``shard-*``
  every `commit_every` images (an atomic rename), so a killed run loses at most its last uncommitted images and
  never leaves a group that reads back wrong; the next run deletes the orphan and recomputes the missing ids.

Each DDP rank writes its own shards through `CacheWriter` (a `BasePredictionWriter`); the reader opens them all.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import socket
import uuid
from pathlib import Path
from urllib.parse import quote

import h5py
import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import BasePredictionWriter
from torch.utils.data import DataLoader, Dataset

from ruslam.atomic_files import atomic_write
from ruslam.data.rgbd_sample import sample_image
from ruslam.errors import InputError, MissingInput

MANIFEST = "teacher.json"
KEYS = ("keypoint_logits", "dense_descriptors", "global_descriptor")


def module_fingerprint(module: torch.nn.Module, extra: dict | None = None) -> str:
    """sha256 of a module's architecture (repr), every weight and buffer (so a VLAD codebook too) and `extra`."""
    digest = hashlib.sha256()
    digest.update(json.dumps({"module": repr(module), "extra": extra or {}}, sort_keys=True, default=str).encode())
    for key, value in sorted(module.state_dict().items()):
        digest.update(key.encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def group_name(image_id: str) -> str:
    return quote(str(image_id), safe="")


class TeacherCacheError(InputError):
    """The teacher cache cannot be built from this source or on this disk (one sentence, no traceback)."""


class TeacherCache:
    """Read side: ``TeacherCache(cache_dir).read(image_id) -> {key: float32 array}``; ``image_id in cache``.

    With `fingerprint`, a cache built by another teacher configuration is refused. Safe to pickle into
    DataLoader workers (files are reopened lazily in each process).
    """

    def __init__(self, cache_dir: str | Path, fingerprint: str | None = None):
        self.cache_dir = Path(cache_dir)
        manifest = read_manifest(self.cache_dir)
        if manifest is None:
            raise MissingInput(f"{self.cache_dir} is not a teacher cache (no {MANIFEST}); build it first.")
        self.fingerprint = manifest["fingerprint"]
        if fingerprint is not None and fingerprint != self.fingerprint:
            raise InputError(mismatch_message(self.cache_dir, self.fingerprint, fingerprint))
        self._index: dict[str, Path] = {}
        for shard in sorted(self.cache_dir.glob("shard-*.h5")):
            with h5py.File(shard, "r") as f:
                if f.attrs.get("teacher_fingerprint") != self.fingerprint:
                    raise InputError(mismatch_message(shard, f.attrs.get("teacher_fingerprint"), self.fingerprint))
                for name in f:
                    self._index.setdefault(name, shard)
        self._files: dict[Path, h5py.File] = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self._index)

    def __contains__(self, image_id: str) -> bool:
        return group_name(image_id) in self._index

    def read(self, image_id: str) -> dict[str, np.ndarray]:
        name = group_name(image_id)
        if name not in self._index:
            raise KeyError(f"Image {image_id!r} is not in the teacher cache {self.cache_dir}.")
        group = self._file(self._index[name])[name]
        return {key: group[key][()].astype(np.float32) for key in group}

    def _file(self, path: Path) -> h5py.File:
        if self._pid != os.getpid():  # forked into a DataLoader worker: never share HDF5 handles
            self._files, self._pid = {}, os.getpid()
        if path not in self._files:
            self._files[path] = h5py.File(path, "r")
        return self._files[path]

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files = {}

    def __getstate__(self):
        return {**self.__dict__, "_files": {}}


def read_manifest(cache_dir: Path) -> dict | None:
    path = Path(cache_dir) / MANIFEST
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (ValueError, OSError) as err:
        raise InputError(f"Teacher cache manifest {path} is unreadable ({err}); delete the cache folder.") from None


def mismatch_message(where, found, expected) -> str:
    return (
        f"Teacher cache {where} was built by another teacher configuration (fingerprint {str(found)[:12]}..., "
        f"expected {str(expected)[:12]}...); use another cache_dir or delete it to rebuild."
    )


def write_manifest(cache_dir: Path, content: dict) -> None:
    atomic_write(cache_dir / MANIFEST, json.dumps(content, indent=2, sort_keys=True, default=str))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_orphan_shards(cache_dir: Path) -> None:
    """Delete temp shards of this host's processes that died (their images are recomputed)."""
    for tmp in cache_dir.glob(".tmp-*.h5"):
        parts = tmp.name[len(".tmp-") : -len(".h5")].rsplit("-", 2)  # host, pid, uuid
        if len(parts) != 3 or parts[0] != socket.gethostname() or not parts[1].isdigit():
            continue  # another host's process (shared file system) or not ours: left alone
        if not _pid_alive(int(parts[1])):
            tmp.unlink(missing_ok=True)


def _write_group(f: h5py.File, image_id: str, arrays: dict[str, np.ndarray], float16: bool, compression) -> None:
    group = f.create_group(group_name(image_id))
    group.attrs["id"] = str(image_id)
    for key, value in arrays.items():
        data = value.astype(np.float16 if float16 else np.float32)
        group.create_dataset(key, data=data, chunks=data.shape, compression=compression)


class CacheWriter(BasePredictionWriter):
    """Writes each predicted batch into this rank's temp shard; commits (close + rename) every `commit_every`."""

    def __init__(self, cache_dir: Path, fingerprint: str, float16: bool, compression, commit_every: int):
        super().__init__(write_interval="batch")
        self.cache_dir, self.fingerprint, self.float16 = Path(cache_dir), fingerprint, float16
        self.compression, self.commit_every = compression, commit_every
        self._file: h5py.File | None = None
        self._tmp: Path | None = None
        self._count = 0
        self.written = 0
        self.rank = 0

    def _open(self) -> h5py.File:
        if self._file is None:
            self._tmp = self.cache_dir / f".tmp-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex}.h5"
            self._file = h5py.File(self._tmp, "w", libver="latest")
            self._file.attrs["teacher_fingerprint"] = self.fingerprint
            self._count = 0
        return self._file

    def commit(self) -> None:
        if self._file is None:
            return
        self._file.close()
        os.replace(self._tmp, self.cache_dir / f"shard-rank{self.rank}-{uuid.uuid4().hex}.h5")
        self._file, self._tmp = None, None

    def discard(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except Exception:  # noqa: BLE001 (the file is deleted anyway)
                pass
            self._tmp.unlink(missing_ok=True)
            self._file, self._tmp = None, None

    def write_on_batch_end(self, trainer, pl_module, prediction, batch_indices, batch, batch_idx, dataloader_idx):
        if prediction is None:
            return
        self.rank = trainer.global_rank
        try:
            for i, image_id in enumerate(prediction["ids"]):
                if group_name(image_id) in self._open():  # a distributed sampler may repeat an image to pad
                    continue
                arrays = {key: prediction[key][i].numpy() for key in prediction if key != "ids"}
                _write_group(self._file, image_id, arrays, self.float16, self.compression)
                self._count += 1
                self.written += 1
                if self._count >= self.commit_every:
                    self.commit()
        except OSError as err:
            self.discard()
            reason = "the disk is full" if err.errno == errno.ENOSPC else f"writing failed ({err})"
            raise TeacherCacheError(
                f"Caching teacher outputs into {self.cache_dir} stopped because {reason}; the images committed so far "
                f"are kept and a rerun resumes after freeing space."
            ) from None

    def on_predict_end(self, trainer, pl_module) -> None:
        self.commit()

    def on_exception(self, trainer, pl_module, exception) -> None:
        self.discard()


def _load_item(dataset, i: int) -> dict:
    try:
        return dataset[i]
    except (InputError, OSError) as err:  # a bad or unreadable file, named with its index; a bug keeps its traceback
        raise TeacherCacheError(f"Image {i} of the dataset could not be read ({err}).") from None


def missing_indices(dataset, done: set[str]) -> list[int]:
    """Indices whose id is not cached yet (ids from ``dataset.image_id(i)`` when offered, else from the items)."""
    image_id = getattr(dataset, "image_id", None)
    ids = (image_id(i) if image_id else _load_item(dataset, i)["id"] for i in range(len(dataset)))
    return [i for i, name in enumerate(ids) if group_name(str(name)) not in done]


class _CacheInputs(Dataset):
    """The images still missing from the cache, as tensors [3, H, W]."""

    def __init__(self, dataset, indices: list[int]):
        self.dataset, self.indices = dataset, indices

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int) -> dict:
        item = _load_item(self.dataset, self.indices[k])
        image_id, image = str(item["id"]), sample_image(item)
        return {"id": image_id, "image": torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)}


def _collate(items: list[dict]) -> dict:
    shapes = {tuple(it["image"].shape) for it in items}
    if len(shapes) > 1:
        raise TeacherCacheError(f"Images of one batch have different sizes {sorted(shapes)}; use batch_size=1.")
    return {"ids": [it["id"] for it in items], "image": torch.stack([it["image"] for it in items])}


class _TeacherPredictor(pl.LightningModule):
    def __init__(self, teacher: torch.nn.Module):
        super().__init__()
        self.teacher = teacher

    def predict_step(self, batch, batch_idx):
        out = self.teacher(batch["image"])
        return {"ids": batch["ids"], **{k: v.detach().float().cpu() for k, v in out.items()}}


def cached_names(cache_dir: Path) -> set[str]:
    names: set[str] = set()
    for shard in cache_dir.glob("shard-*.h5"):
        with h5py.File(shard, "r") as f:
            names.update(f)
    return names


def build_cache(
    dataset,
    teacher: torch.nn.Module,
    cache_dir: str | Path,
    config: dict | None = None,
    float16: bool = True,
    compression: str | None = "lzf",
    batch_size: int = 1,
    num_workers: int = 0,
    commit_every: int = 256,
    accelerator: str = "cpu",
    devices: int | str = 1,
    strategy: str = "auto",
) -> TeacherCache:
    """Run `teacher` once on every image of `dataset` ({"id", "image" HxWx3 in [0, 1]}) not yet in `cache_dir`.

    `config`: the caller's settings that change the targets (e.g. resolution, dataset), hashed with the teacher's
    weights and codebook into the fingerprint. Returns the reader.
    """
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    if hasattr(teacher, "prepare"):
        teacher.prepare(dataset, cache_dir)  # e.g. fit the VLAD codebook, saved beside the cache
    fingerprint = module_fingerprint(teacher, config)
    manifest = read_manifest(cache_dir)
    if manifest is not None and manifest.get("fingerprint") != fingerprint:
        raise InputError(mismatch_message(cache_dir, manifest.get("fingerprint"), fingerprint))
    if manifest is None:
        write_manifest(cache_dir, {"fingerprint": fingerprint, "config": config or {}, "float16": float16})
    remove_orphan_shards(cache_dir)
    missing = missing_indices(dataset, cached_names(cache_dir))
    if missing:
        writer = CacheWriter(cache_dir, fingerprint, float16, compression, commit_every)
        loader = DataLoader(_CacheInputs(dataset, missing), batch_size=batch_size, num_workers=num_workers,
                            collate_fn=_collate, shuffle=False)
        trainer = pl.Trainer(accelerator=accelerator, devices=devices, strategy=strategy, callbacks=[writer],
                             logger=False, enable_checkpointing=False, enable_progress_bar=False,
                             enable_model_summary=False)
        trainer.predict(_TeacherPredictor(teacher), dataloaders=loader, return_predictions=False)
        trainer.strategy.barrier("teacher_cache_committed")  # every rank's last shard is committed before reading
    return TeacherCache(cache_dir, fingerprint)

