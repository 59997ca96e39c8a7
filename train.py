"""Fit a neural surface: python train.py experiment=bunny_sdf [key=value ...]"""

import hydra
from omegaconf import DictConfig

from neuralsurf.cli import train


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    train(cfg)


if __name__ == "__main__":
    main()
