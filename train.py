"""Entry point: `python train.py [overrides]`, `python train.py -m ...` for sweeps (see conf/train.yaml)."""

import hydra
from omegaconf import DictConfig

from ruslam.cli import run_cli
from ruslam.train import train


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float | None:
    return run_cli(train, cfg)


if __name__ == "__main__":
    main()
