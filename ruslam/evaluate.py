"""`evaluate(cfg)`: run the evaluation task chosen by `task=` (each task module exposes `run(cfg) -> dict`)."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import get_method
from omegaconf import DictConfig

from ruslam.config_checks import check_evaluate


def evaluate(cfg: DictConfig) -> dict:
    check_evaluate(cfg)  # before the task module (and torch) is imported
    Path(cfg.out_dir).mkdir(parents=True, exist_ok=True)
    return get_method(cfg.task.runner)(cfg)
