"""Neural against classical on the same scenes: python evaluate.py [suite=quick] [methods=[...]] [scenes=[...]]"""

import hydra
from omegaconf import DictConfig

from neuralsurf.cli import evaluate


@hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    main()
