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
from ruslam.errors import InputError
from ruslam.models.export import export_weights, load_uwnet

REPORTED = (("val/detector", "detector (L3, soft CE)"), ("val/local", "local descriptors (L2)"),
            ("val/global", "global descriptor (L1)"), ("val/correspondence", "correspondence (InfoNCE)"),
            ("val/reliability", "reliability (BCE)"), ("val/repeatability", "repeatability (1 - correlation)"),
            ("val/loss", "total"))


def _instantiate_all(group: DictConfig | None) -> list:
    return [instantiate(conf) for conf in (group or {}).values() if conf is not None and "_target_" in conf]


# Blocks a fine-tuning run may add to the weights it starts from: zero-initialised, so the start is unchanged.
GROWABLE = {"keypoint_neighbourhood": "kp_neighbours.", "keypoint_cell": "kp_fine_"}


def load_initial_weights(net: torch.nn.Module, path: str | Path) -> None:
    """Fine-tuning: start from trained weights (exported .pt or Lightning .ckpt); unlike ckpt_path, the optimizer,
    learning rate and epoch count start afresh from the config."""
    source = load_uwnet(path)
    differ = [k for k in net.config if source.config.get(k) != net.config[k]]
    added = [k for k in differ if k in GROWABLE and net.config[k]]  # the rebuilt source has every key: False there
    if set(differ) - set(added):
        k = next(k for k in differ if k not in added)
        raise InputError(f"init_weights={path} holds a UWNet with {k}={source.config.get(k)!r}, but the configured "
                         f"model has {k}={net.config[k]!r}; use weights of the same architecture.")
    missing, unexpected = net.load_state_dict(source.state_dict(), strict=False)
    grown = tuple(GROWABLE[k] for k in added)
    if unexpected or any(not k.startswith(grown) for k in missing):  # only the added blocks may be new
        raise InputError(f"init_weights={path} does not fit the configured model (missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]}).")


def format_report(before: dict, after: dict, start: str = "untrained") -> str:
    lines = [f"{'held-out loss':<28}{start:>12}{'trained':>12}"]
    for key, label in REPORTED:
        if key in before and key in after:
            lines.append(f"{label:<28}{before[key]:>12.4f}{after[key]:>12.4f}")
    return "\n".join(lines)


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
