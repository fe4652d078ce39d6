"""Entry point: `python train.py [overrides]`, `python train.py -m ...` for sweeps (see conf/train.yaml)."""

import hydra
from omegaconf import DictConfig

from ruslam.cli import run_cli
from ruslam.config_checks import check_train


def checked_train(cfg: DictConfig) -> float | None:
    check_train(cfg)  # a bad input is reported before torch, Lightning and the models are even imported
    from ruslam.train import train

    return train(cfg)


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float | None:
    return run_cli(checked_train, cfg)


if __name__ == "__main__":
    main()
