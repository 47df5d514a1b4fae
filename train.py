#!/usr/bin/env python
"""Train FisheyeDepth (or an ablation): ``python train.py [+experiment=ablation_fft_only] [key=value ...]``.

After training, the best checkpoint is evaluated on the test split into ``results.json`` in the run's
output folder. Sweeps: ``python train.py -m +experiment=ablation_full,ablation_fft_only seed=0,1``.
"""

import hydra
from omegaconf import DictConfig

from fisheyedepth.cli import run_command
from fisheyedepth.cli.train import train


@hydra.main(config_path="conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run_command(train, cfg)


if __name__ == "__main__":
    main()
