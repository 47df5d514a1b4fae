#!/usr/bin/env python
"""Evaluate a checkpoint on a test split: ``python eval.py ckpt_path=PATH [data=kitti360] [...]``."""

import hydra
from omegaconf import DictConfig

from fisheyedepth.entrypoints import eval_checkpoint, run_command


@hydra.main(config_path="conf", config_name="eval", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run_command(eval_checkpoint, cfg)


if __name__ == "__main__":
    main()
