"""`DistillationDataModule`: in-air RGB-D source + cached teacher targets -> (degraded student input, targets).

The teacher sees the clean in-air image once (`prepare_data` builds the HDF5 cache); every training sample then
pairs those cached targets with a pseudo-underwater version of the image (synthesis on the student input only,
seeded by (seed, epoch, index) so a run is reproducible yet sees new water every epoch), photometric jitter, and the
geometric warp that moves the targets with it (`ruslam.training.augment`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytorch_lightning as pl
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader, Dataset

from ruslam.errors import InputError
from ruslam.training.augment import seeded_generator, warp_image, warp_targets


def _plain(conf) -> dict | None:
    if conf is None:
        return None
    return OmegaConf.to_container(conf, resolve=True) if isinstance(conf, DictConfig) else dict(conf)


def _build(conf):
    return None if conf is None else instantiate(conf)


class DistillationDataset(Dataset):
    def __init__(self, source, indices, cache, synthesis=None, photometric=None, geometric=None, seed=0,
                 vary_per_epoch=True, pair_views=False):
        self.source, self.indices, self.cache = source, list(indices), cache
        # Two independently degraded and warped views per image (``pair`` + ``homography_ab``) for the
        # correspondence loss.
        self.pair_views = pair_views
        self.synthesis, self.photometric, self.geometric = synthesis, photometric, geometric
        self.seed, self.vary_per_epoch, self.epoch = seed, vary_per_epoch, 0

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        index = self.indices[i]
        item = self.source[index]
        targets = {k: torch.from_numpy(v) for k, v in self.cache.read(str(item["id"])).items()}
        sample, hom_a = self._view(item, targets, index, 0)
        if not self.pair_views:
            return sample
        second, hom_b = self._view(item, targets, index, 1)
        sample["pair"] = second
        sample["homography_ab"] = (hom_b @ torch.linalg.inv(hom_a)).float()  # view-A pixels -> view-B pixels
        return sample

    def _view(self, item: dict, targets: dict, index: int, view: int) -> tuple[dict, torch.Tensor]:
        """One degraded, warped student input with its warped targets, and the pixel homography used (float64).
        View 0 keeps the seeds of the single-view pipeline; view 1 draws independent water, jitter and warp."""
        rgb = torch.from_numpy(np.ascontiguousarray(item["image"], np.float32)).permute(2, 0, 1)
        epoch = self.epoch if self.vary_per_epoch else 0
        if self.synthesis is not None:  # invalid depth (NaN) stays invalid: eq. 4 shows it as infinitely far
            depth = torch.from_numpy(np.ascontiguousarray(item["depth"], np.float32))
            key = index + epoch * len(self.source) + view * 1_000_003
            rgb = self.synthesis(rgb[None], depth[None], [key])[0].float()
        gen = seeded_generator(self.seed, epoch, index, *([view] if view else []))
        if self.photometric is not None:
            rgb = self.photometric(rgb, gen)
        hom = torch.eye(3, dtype=torch.float64)
        if self.geometric is not None:
            hom = self.geometric.sample(rgb.shape[1], rgb.shape[2], gen)
            rgb = warp_image(rgb, hom)
            out = warp_targets(targets, hom)
        else:
            out = {**targets, "mask": torch.ones(targets["keypoint_logits"].shape[1:])}
        return {"image": rgb, **out}, hom


class PreparedSource:
    """The first `limit` samples of a source, resized to `size` (h, w), optionally kept in memory.

    Training resolution is a property of the run, not of the source: the embedded default trains at 120x160 on
    images the procedural source renders at 240x320; procedural rendering then happens once, not every epoch.
    """

    def __init__(self, source, limit: int | None = None, size: tuple[int, int] | None = None, preload: bool = True):
        self.source, self.size = source, tuple(size) if size else None
        self.length = min(len(source), limit) if limit else len(source)
        self.items = [self._load(i) for i in range(self.length)] if preload else None

    def _load(self, i: int) -> dict:
        item = dict(self.source[i])
        if self.size and tuple(item["image"].shape[:2]) != self.size:
            h, w = self.size
            item["image"] = cv2.resize(item["image"], (w, h), interpolation=cv2.INTER_AREA)
            item["depth"] = cv2.resize(item["depth"], (w, h), interpolation=cv2.INTER_NEAREST)
        return item

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i: int) -> dict:
        if not 0 <= i < self.length:
            raise IndexError(f"index {i} out of range for {self.length} training images")
        return self.items[i] if self.items is not None else self._load(i)


class DistillationDataModule(pl.LightningDataModule):
    """Configs (not objects) for source/teacher/synthesis/augmentations, built lazily in each process."""

    def __init__(self, source: dict, teacher: dict, cache_root: str = "~/.cache/ruslam/teacher", val_size: int = 32,
                 split_seed: int = 0, batch_size: int = 16, num_workers: int = 0, seed: int = 0, preload: bool = True,
                 limit_images: int | None = None, image_size: tuple[int, int] | None = None,
                 synthesis: dict | None = None, photometric: dict | None = None, geometric: dict | None = None,
                 teacher_batch_size: int = 8, val_overrides: dict | None = None, pair_views: bool = False):
        super().__init__()
        self.source_conf, self.teacher_conf = _plain(source), _plain(teacher)
        self.synthesis_conf, self.photometric_conf = _plain(synthesis), _plain(photometric)
        self.geometric_conf = _plain(geometric)
        self.val_size, self.split_seed, self.batch_size = val_size, split_seed, batch_size
        self.num_workers, self.seed, self.preload = num_workers, seed, preload
        self.teacher_batch_size = teacher_batch_size
        self.pair_views = pair_views
        # e.g. {split: test}: the held-out set is the source built with these options (NYU's 200 test images)
        # instead of val_size images carved out of the training source.
        self.val_overrides = _plain(val_overrides)
        self.limit_images = limit_images
        self.image_size = tuple(image_size) if image_size else None
        if self.image_size and (len(self.image_size) != 2 or self.image_size[0] % 8 or self.image_size[1] % 8):
            raise InputError(f"image_size must be [height, width], multiples of 8; got {list(self.image_size)}.")
        # Targets depend on the source and the resolution, not on how many images are used: a longer run with a
        # larger limit_images reuses (and extends) the same cache.
        self.cache_config = {"source": self.source_conf, "image_size": self.image_size}
        key = json.dumps({**self.cache_config, "teacher": self.teacher_conf}, sort_keys=True, default=str)
        self.cache_dir = Path(cache_root).expanduser() / hashlib.sha1(key.encode()).hexdigest()[:12]
        self.train_set: DistillationDataset | None = None
        self.val_set: DistillationDataset | None = None
        self._source_cache = None
        self._val_source_cache = None

    def _source(self):
        if self._source_cache is None:  # rendered/read once per process, shared by the teacher cache and training
            source = PreparedSource(instantiate(self.source_conf), self.limit_images, self.image_size, self.preload)
            if self.val_overrides is None and len(source) <= self.val_size:
                raise InputError(f"The RGB-D source gives {len(source)} images; it needs more than "
                                 f"val_size={self.val_size}.")
            self._source_cache = source
        return self._source_cache

    def _val_source(self):
        if self.val_overrides is None:
            return None
        if self._val_source_cache is None:
            conf = {**self.source_conf, **self.val_overrides}
            self._val_source_cache = PreparedSource(instantiate(conf), None, self.image_size, self.preload)
        return self._val_source_cache

    def prepare_data(self) -> None:
        from ruslam.data.teacher_cache import build_cache  # noqa: PLC0415 (teacher stack only when caching)

        teacher = instantiate(self.teacher_conf)
        for source in (self._source(), self._val_source()):
            if source is not None:
                build_cache(source, teacher, self.cache_dir, config=self.cache_config,
                            batch_size=self.teacher_batch_size, **self._cache_device())

    def _cache_device(self) -> dict:
        """The teacher runs on the training accelerator, on this process's device. Lightning calls prepare_data
        on one process per node while the others wait, so the cache is built by one device, not all ranks."""
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return {}
        device = trainer.strategy.root_device
        return {"accelerator": {"cuda": "gpu"}.get(device.type, device.type),
                "devices": [device.index] if device.index is not None else 1}

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        from ruslam.data.teacher_cache import TeacherCache  # noqa: PLC0415

        source = self._source()
        first = source[0]["image"]
        if first.shape[0] % 8 or first.shape[1] % 8:
            raise InputError(f"Training images must have height and width multiples of 8, got {first.shape[:2]}.")
        cache = TeacherCache(self.cache_dir)
        val_source = self._val_source()
        if val_source is None:
            order = np.random.default_rng(self.split_seed).permutation(len(source))
            val_idx, train_idx = sorted(order[: self.val_size].tolist()), sorted(order[self.val_size:].tolist())
            val_source = source
        else:
            val_idx, train_idx = list(range(len(val_source))), list(range(len(source)))
        synthesis, photometric = _build(self.synthesis_conf), _build(self.photometric_conf)
        geometric = _build(self.geometric_conf)
        self.train_set = DistillationDataset(source, train_idx, cache, synthesis, photometric, geometric, self.seed,
                                             pair_views=self.pair_views)
        # Held-out set: same degradations and warps, but fixed per image so epochs compare like with like.
        self.val_set = DistillationDataset(val_source, val_idx, cache, synthesis, None, geometric, self.seed + 1,
                                           vary_per_epoch=False, pair_views=self.pair_views)

    def set_epoch(self, epoch: int) -> None:
        if self.train_set is not None:
            self.train_set.epoch = epoch

    def train_dataloader(self) -> DataLoader:
        drop_last = len(self.train_set) > self.batch_size  # a tiny set still gives one (smaller) batch
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True, drop_last=drop_last,
                          num_workers=self.num_workers, persistent_workers=False)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size, shuffle=False, num_workers=self.num_workers)
