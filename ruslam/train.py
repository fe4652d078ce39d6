"""`train(cfg)`: distill UWNet (paper 3.2.2) from a composed `conf/train.yaml`; plain function, tests call it.

It reports what training bought: the held-out losses of the untrained network next to those of the trained one,
then writes the fp16 weights-only file that `load_extractor(path)` reads.
"""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

from ruslam.config_checks import check_train
from ruslam.models.export import export_weights
from ruslam.training.common import format_report, load_initial_weights


def _instantiate_all(group: DictConfig | None) -> list:
    return [instantiate(conf) for conf in (group or {}).values() if conf is not None and "_target_" in conf]


def train(cfg: DictConfig) -> float | None:
    """Fit, report before/after held-out losses, export weights; returns the final held-out loss (for sweeps)."""
    check_train(cfg)
    if cfg.get("online"):  # no teacher cache: views and targets on the fly on the device (conf/experiment/fine_cells)
        from ruslam.training.online import train_online  # noqa: PLC0415

        return train_online(cfg)
    pl.seed_everything(cfg.seed, workers=True)
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg.torch_threads))
    out_dir = Path(cfg.out_dir)
    datamodule = instantiate(cfg.datamodule, source=cfg.data, teacher=cfg.teacher)
    module = instantiate(cfg.model)
    if cfg.get("init_weights"):
        load_initial_weights(module.net, cfg.init_weights)
    trainer: pl.Trainer = instantiate(cfg.trainer, logger=_instantiate_all(cfg.get("logger")) or False,
                                      callbacks=_instantiate_all(cfg.get("callbacks")))
    before = trainer.validate(module, datamodule=datamodule, verbose=False)[0]
    trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
    after = trainer.validate(module, datamodule=datamodule, verbose=False)[0]
    if not trainer.is_global_zero:
        return None
    ckpt = getattr(trainer.checkpoint_callback, "last_model_path", "") or ""
    weights = out_dir / cfg.get("export_name", "uwnet.pt")
    export_weights(module.net, weights)
    print(format_report(before, after, "initial" if cfg.get("init_weights") else "untrained"))
    print(f"Lightning checkpoint: {ckpt or '(none: checkpointing disabled)'}")
    print(f"fp16 weights for load_extractor: {weights}")
    return float(after["val/loss"])
