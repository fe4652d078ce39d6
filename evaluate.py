"""Entry point: `python evaluate.py task=synthesis|matching|slam [overrides]` (see conf/evaluate.yaml)."""

import hydra
from omegaconf import DictConfig

from ruslam.cli import run_cli
from ruslam.evaluate import evaluate


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    run_cli(evaluate, cfg)


if __name__ == "__main__":
    main()
